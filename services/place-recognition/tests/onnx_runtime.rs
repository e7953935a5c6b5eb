//! onnxruntime loads a generated ONNX descriptor head and computes what we compute by hand.

use doorslam_place_recognition::{onnx, DescriptorModel, PlaceRecognitionError};

// W is 3x2 row-major, b has 2 entries.
const W: [f32; 6] = [1.0, 0.0, 0.0, 1.0, 1.0, 1.0];
const B: [f32; 2] = [0.0, 1.0];

#[test]
fn generated_model_runs_and_matches_hand_computation() {
    let bytes = onnx::projection_head(3, 2, &W, &B).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("head.onnx");
    std::fs::write(&path, &bytes).unwrap();

    let mut model = DescriptorModel::from_file(&path).unwrap();
    assert_eq!((model.input_dim(), model.output_dim()), (3, 2));

    // Row 1: [3,4,0]·W + b = [3,5] -> /sqrt(34).  Row 2: [1,-1,2]·W + b = [3,2] -> /sqrt(13).
    let out = model.describe(&[3.0, 4.0, 0.0, 1.0, -1.0, 2.0]).unwrap();
    let s34 = 34f32.sqrt();
    let s13 = 13f32.sqrt();
    let want = [3.0 / s34, 5.0 / s34, 3.0 / s13, 2.0 / s13];
    assert_eq!(out.len(), 4);
    for (got, want) in out.iter().zip(want) {
        assert!((got - want).abs() < 1e-6, "got {out:?}, want {want:?}");
    }

    // The same model from memory gives the same answer.
    let mut from_mem = DescriptorModel::from_bytes(&bytes, "generated").unwrap();
    assert_eq!(
        from_mem.describe(&[3.0, 4.0, 0.0]).unwrap(),
        out[..2].to_vec()
    );
}

#[test]
fn bad_models_and_inputs_are_clear_errors() {
    let err = DescriptorModel::from_bytes(b"definitely not onnx", "garbage.onnx")
        .err()
        .unwrap();
    assert!(matches!(err, PlaceRecognitionError::Load { .. }), "{err}");
    assert!(err.to_string().contains("garbage.onnx"), "{err}");

    let missing = std::path::Path::new("/nonexistent/model.onnx");
    let err = DescriptorModel::from_file(missing).err().unwrap();
    assert!(err.to_string().contains("/nonexistent/model.onnx"), "{err}");

    let mut model =
        DescriptorModel::from_bytes(&onnx::projection_head(3, 2, &W, &B).unwrap(), "head").unwrap();
    let err = model.describe(&[1.0, 2.0]).unwrap_err();
    assert!(
        matches!(err, PlaceRecognitionError::InputShape { got: 2, dim: 3 }),
        "{err}"
    );
}
