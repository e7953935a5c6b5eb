//! Writes ONNX `ModelProto` files (protobuf wire format) for small fixed graphs.
//!
//! Only what the descriptor head needs is implemented: float tensors as initializers,
//! nodes with int attributes, and graph inputs/outputs with a dynamic batch dimension.
//! Field numbers follow `onnx.proto` (ONNX IR version 8, opset 17).

/// ONNX IR version written into the model.
pub const IR_VERSION: u64 = 8;
/// Default-domain opset the nodes are written against.
pub const OPSET: u64 = 17;
const ELEM_FLOAT: u64 = 1;

/// Protobuf encoding of one message, built field by field.
#[derive(Default)]
struct Msg(Vec<u8>);

impl Msg {
    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.0.push((v as u8) | 0x80);
            v >>= 7;
        }
        self.0.push(v as u8);
    }
    fn key(&mut self, field: u32, wire_type: u8) {
        self.varint(((field as u64) << 3) | wire_type as u64);
    }
    fn uint(mut self, field: u32, v: u64) -> Self {
        self.key(field, 0);
        self.varint(v);
        self
    }
    fn bytes(mut self, field: u32, b: &[u8]) -> Self {
        self.key(field, 2);
        self.varint(b.len() as u64);
        self.0.extend_from_slice(b);
        self
    }
    fn str(self, field: u32, s: &str) -> Self {
        self.bytes(field, s.as_bytes())
    }
    fn msg(self, field: u32, m: Msg) -> Self {
        self.bytes(field, &m.0)
    }
}

/// One dimension of a tensor shape: fixed size or a symbolic name (e.g. the batch).
#[derive(Debug, Clone)]
pub enum Dim {
    Fixed(u64),
    Named(&'static str),
}

fn value_info(name: &str, dims: &[Dim]) -> Msg {
    let shape = dims.iter().fold(Msg::default(), |shape, d| {
        let dim = match d {
            Dim::Fixed(v) => Msg::default().uint(1, *v),
            Dim::Named(n) => Msg::default().str(2, n),
        };
        shape.msg(1, dim)
    });
    let tensor_type = Msg::default().uint(1, ELEM_FLOAT).msg(2, shape);
    let type_proto = Msg::default().msg(1, tensor_type);
    Msg::default().str(1, name).msg(2, type_proto)
}

fn float_tensor(name: &str, dims: &[u64], values: &[f32]) -> Msg {
    let mut t = dims.iter().fold(Msg::default(), |t, &d| t.uint(1, d));
    t = t.uint(2, ELEM_FLOAT).str(8, name);
    let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    t.bytes(9, &raw)
}

fn node(op: &str, name: &str, inputs: &[&str], outputs: &[&str], int_attrs: &[(&str, i64)]) -> Msg {
    let mut n = Msg::default();
    for i in inputs {
        n = n.str(1, i);
    }
    for o in outputs {
        n = n.str(2, o);
    }
    n = n.str(3, name).str(4, op);
    for (attr, v) in int_attrs {
        // AttributeProto: name = 1, i = 3, type = 20 (INT = 2).
        n = n.msg(
            5,
            Msg::default().str(1, attr).uint(3, *v as u64).uint(20, 2),
        );
    }
    n
}

/// The descriptor projection head: `descriptor = L2normalize(input · W + b)` per row.
///
/// `input` is `[batch, d_in]`, `W` is `[d_in, d_out]` row-major, `b` is `[d_out]`.
/// Returns the bytes of an `.onnx` file; `None` if the matrix sizes disagree.
pub fn projection_head(d_in: usize, d_out: usize, w: &[f32], b: &[f32]) -> Option<Vec<u8>> {
    if d_in == 0 || d_out == 0 || w.len() != d_in * d_out || b.len() != d_out {
        return None;
    }
    let graph = Msg::default()
        .msg(
            1,
            node("MatMul", "project", &["input", "W"], &["projected"], &[]),
        )
        .msg(
            1,
            node("Add", "bias", &["projected", "b"], &["biased"], &[]),
        )
        .msg(
            1,
            node(
                "LpNormalization",
                "normalize",
                &["biased"],
                &["descriptor"],
                &[("axis", -1), ("p", 2)],
            ),
        )
        .str(2, "doorslam_descriptor_head")
        .msg(5, float_tensor("W", &[d_in as u64, d_out as u64], w))
        .msg(5, float_tensor("b", &[d_out as u64], b))
        .msg(
            11,
            value_info("input", &[Dim::Named("batch"), Dim::Fixed(d_in as u64)]),
        )
        .msg(
            12,
            value_info(
                "descriptor",
                &[Dim::Named("batch"), Dim::Fixed(d_out as u64)],
            ),
        );
    Some(model(graph))
}

/// A small image-descriptor model with the NetVLAD contract (`model/README.md`): input
/// `[batch, channels, height, width]`, output `[batch, d_out]`,
/// `descriptor = L2normalize(flatten(image) · W + b)`.
///
/// `W` is `[channels·height·width, d_out]` row-major, `b` is `[d_out]`. Tests use it in
/// place of the real network (a random `W` is a random projection of the pixels: views of
/// the same image land near each other). `None` if the sizes disagree.
pub fn image_head(
    channels: usize,
    height: usize,
    width: usize,
    d_out: usize,
    w: &[f32],
    b: &[f32],
) -> Option<Vec<u8>> {
    let d_in = channels * height * width;
    if d_in == 0 || d_out == 0 || w.len() != d_in * d_out || b.len() != d_out {
        return None;
    }
    let graph = Msg::default()
        .msg(
            1,
            node(
                "Flatten",
                "flatten",
                &["image"],
                &["pixels"],
                &[("axis", 1)],
            ),
        )
        .msg(
            1,
            node("MatMul", "project", &["pixels", "W"], &["projected"], &[]),
        )
        .msg(
            1,
            node("Add", "bias", &["projected", "b"], &["biased"], &[]),
        )
        .msg(
            1,
            node(
                "LpNormalization",
                "normalize",
                &["biased"],
                &["descriptor"],
                &[("axis", -1), ("p", 2)],
            ),
        )
        .str(2, "doorslam_test_image_head")
        .msg(5, float_tensor("W", &[d_in as u64, d_out as u64], w))
        .msg(5, float_tensor("b", &[d_out as u64], b))
        .msg(
            11,
            value_info(
                "image",
                &[
                    Dim::Named("batch"),
                    Dim::Fixed(channels as u64),
                    Dim::Fixed(height as u64),
                    Dim::Fixed(width as u64),
                ],
            ),
        )
        .msg(
            12,
            value_info(
                "descriptor",
                &[Dim::Named("batch"), Dim::Fixed(d_out as u64)],
            ),
        );
    Some(model(graph))
}

/// A `ModelProto` around `graph` (IR version, producer, opset).
fn model(graph: Msg) -> Vec<u8> {
    let opset = Msg::default().str(1, "").uint(2, OPSET);
    Msg::default()
        .uint(1, IR_VERSION)
        .str(2, "doorslam")
        .str(3, env!("CARGO_PKG_VERSION"))
        .msg(7, graph)
        .msg(8, opset)
        .0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varints_encode_like_protobuf() {
        let mut m = Msg::default();
        m.varint(300);
        assert_eq!(m.0, [0xAC, 0x02]);
        // Negative int64 attributes are 10-byte varints (two's complement).
        let mut m = Msg::default();
        m.varint(-1i64 as u64);
        assert_eq!(m.0.len(), 10);
    }

    #[test]
    fn mismatched_sizes_are_rejected() {
        assert!(projection_head(3, 2, &[0.0; 5], &[0.0; 2]).is_none());
        assert!(projection_head(3, 2, &[0.0; 6], &[0.0; 3]).is_none());
        assert!(image_head(1, 2, 3, 2, &[0.0; 11], &[0.0; 2]).is_none());
    }
}
