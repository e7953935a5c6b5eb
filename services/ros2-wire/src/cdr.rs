//! The CDR encoding ROS 2 puts on the wire and in bags: little-endian, a 4-byte
//! encapsulation header (`00 01 00 00`, CDR_LE), every primitive aligned to its own size
//! counted from the end of that header, strings as a `u32` length that counts the closing
//! NUL, sequences as a `u32` element count followed by the elements.

use crate::WireError;

/// The CDR_LE encapsulation header (representation id 0x0001, options 0).
pub const ENCAPSULATION_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Writes one CDR payload. The writes themselves cannot fail; what a payload cannot hold
/// (a string with a NUL, a sequence longer than `u32::MAX`) is remembered and returned
/// by [`CdrWriter::finish`], so a message's `write` stays a plain list of its fields.
#[derive(Debug, Clone)]
pub struct CdrWriter {
    buf: Vec<u8>,
    error: Option<WireError>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    pub fn new() -> Self {
        Self {
            buf: ENCAPSULATION_LE.to_vec(),
            error: None,
        }
    }

    /// Pads with zeros so that the next write of `size` bytes starts at a multiple of
    /// `size` from the end of the encapsulation header.
    fn align(&mut self, size: usize) {
        let offset = self.buf.len() - ENCAPSULATION_LE.len();
        let pad = (size - offset % size) % size;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    pub fn bool(&mut self, v: bool) {
        self.buf.push(u8::from(v));
    }

    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A sequence's element count.
    pub fn seq_len(&mut self, n: usize) {
        match u32::try_from(n) {
            Ok(n) => self.u32(n),
            Err(_) => {
                self.fail(WireError::TooLong { len: n });
                self.u32(0);
            }
        }
    }

    /// A string: length with the NUL, the bytes, the NUL.
    pub fn string(&mut self, s: &str) {
        if s.as_bytes().contains(&0) {
            self.fail(WireError::NulInString(s.replace('\0', "\\0")));
        }
        self.seq_len(s.len() + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    /// A `uint8[]` (or `byte[]`): count, then the bytes unpadded.
    pub fn bytes(&mut self, b: &[u8]) {
        self.seq_len(b.len());
        self.buf.extend_from_slice(b);
    }

    fn fail(&mut self, e: WireError) {
        self.error.get_or_insert(e);
    }

    /// The payload, header included, or the first thing it could not hold.
    pub fn finish(self) -> Result<Vec<u8>, WireError> {
        match self.error {
            Some(e) => Err(e),
            None => Ok(self.buf),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_counts_from_the_end_of_the_header() {
        let mut w = CdrWriter::new();
        w.u8(7);
        w.f64(1.0);
        let b = w.finish().unwrap();
        // 4 header + 1 byte + 7 padding (offset 1 -> 8) + 8.
        assert_eq!(b.len(), 4 + 8 + 8);
        assert_eq!(&b[..5], &[0, 1, 0, 0, 7]);
        assert!(b[5..12].iter().all(|&x| x == 0));
        assert_eq!(&b[12..], &1.0f64.to_le_bytes());
    }

    #[test]
    fn a_string_counts_its_nul_and_a_nul_inside_is_an_error() {
        let mut w = CdrWriter::new();
        w.string("ab");
        assert_eq!(
            w.finish().unwrap(),
            vec![0, 1, 0, 0, 3, 0, 0, 0, b'a', b'b', 0]
        );
        let mut w = CdrWriter::new();
        w.string("a\0b");
        assert!(matches!(w.finish(), Err(WireError::NulInString(_))));
    }
}
