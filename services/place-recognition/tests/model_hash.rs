//! The place-recognition files deploy/setup builds are reproducible: the NetVLAD model and
//! the bag-of-words vocabulary in `$DOORSLAM_HOME/models` (default `~/.cache/doorslam`)
//! have exactly the sha256 recorded in `model/RECORDED.sha256` (and `model/README.md`).
//! `build_model.py` seeds every random choice, fixes the BLAS and onnxruntime thread
//! counts and pins the BLAS kernels (`OPENBLAS_CORETYPE=Haswell`), and deploy/setup pins the
//! Python packages it trains with, so a fresh machine of this kind (AVX2, no AVX-512: what
//! else the bytes depend on is in model/README.md) builds the same bytes; a change to the
//! build that changes them must record the new hash.

use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

fn models_dir() -> PathBuf {
    std::env::var_os("DOORSLAM_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/doorslam")))
        .expect("neither DOORSLAM_HOME nor HOME is set")
        .join("models")
}

/// `(sha256, file name)` rows of `model/RECORDED.sha256` (the `sha256sum` format).
fn recorded() -> Vec<(String, String)> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("model/RECORDED.sha256");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let (hash, name) = l
                .split_once("  ")
                .unwrap_or_else(|| panic!("{}: not `HASH  FILE`: {l}", path.display()));
            (hash.to_string(), name.to_string())
        })
        .collect()
}

#[test]
fn the_built_model_and_vocabulary_have_the_recorded_hashes() {
    let rows = recorded();
    let names: Vec<&str> = rows.iter().map(|(_, n)| n.as_str()).collect();
    // The files the set-up builds are the ones recorded.
    assert!(names.contains(&doorslam_place_recognition::netvlad::DEFAULT_MODEL_FILE));
    assert!(names.contains(&doorslam_place_recognition::bow::DEFAULT_VOCABULARY_FILE));
    for (hash, name) in rows {
        let path = models_dir().join(&name);
        let bytes = std::fs::read(&path)
            .unwrap_or_else(|e| panic!("{}: {e} (deploy/setup builds it)", path.display()));
        let digest: String = Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        assert_eq!(
            digest,
            hash,
            "{} is not the recorded build (model/RECORDED.sha256): a stale cache (delete it and \
             run deploy/setup), other package versions than deploy/setup pins, a CPU whose \
             onnxruntime kernels differ (AVX-512; model/README.md \"What the bytes depend \
             on\"), or a change to build_model.py whose new hash must be recorded",
            path.display()
        );
    }
}
