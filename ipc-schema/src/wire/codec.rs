//! Byte-level encoding shared by every message: little-endian fixed-width values,
//! canonical LEB128 varints, IEEE half floats, and a bounded reader.
//!
//! Every encoding is canonical (one byte string per value), so a decoded message
//! re-encodes to exactly the bytes it came from.

use super::WireError;

/// Where an encoder writes: a buffer, or a counter that only measures (`encoded_len`).
/// Both run the same code, so the measured length is the written length by construction.
pub(crate) trait Sink {
    fn put(&mut self, bytes: &[u8]);
    /// Bytes written so far (the offset of the next field, for error messages).
    fn offset(&self) -> usize;

    fn u8(&mut self, v: u8) {
        self.put(&[v]);
    }
    fn u16(&mut self, v: u16) {
        self.put(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.put(&v.to_le_bytes());
    }
    /// Signed value as a zigzag varint (0, -1, 1, -2, … → 0, 1, 2, 3, …): small magnitudes
    /// of either sign take few bytes.
    fn zigzag(&mut self, v: i64) {
        self.varint(((v << 1) ^ (v >> 63)) as u64);
    }
    /// Unsigned LEB128: 7 bits per byte, least significant group first, high bit = more.
    fn varint(&mut self, mut v: u64) {
        let mut buf = [0u8; 10];
        let mut n = 0;
        loop {
            let b = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                buf[n] = b;
                n += 1;
                break;
            }
            buf[n] = b | 0x80;
            n += 1;
        }
        self.put(&buf[..n]);
    }
}

impl Sink for Vec<u8> {
    fn put(&mut self, bytes: &[u8]) {
        self.extend_from_slice(bytes);
    }
    fn offset(&self) -> usize {
        self.len()
    }
}

/// A sink that counts bytes and stores none.
#[derive(Default)]
pub(crate) struct Counter(pub usize);

impl Sink for Counter {
    fn put(&mut self, bytes: &[u8]) {
        self.0 += bytes.len();
    }
    fn offset(&self) -> usize {
        self.0
    }
}

/// Reads fields front to back from untrusted bytes; never reads or allocates past the end.
pub(crate) struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub fn new(buf: &'a [u8]) -> Self {
        Self { buf, pos: 0 }
    }

    /// Offset of the next unread byte.
    pub fn offset(&self) -> usize {
        self.pos
    }

    pub fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    pub fn take(&mut self, field: &'static str, n: usize) -> Result<&'a [u8], WireError> {
        if n > self.remaining() {
            return Err(WireError::Truncated {
                field,
                offset: self.pos,
                needed: n,
                available: self.remaining(),
            });
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    pub fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], WireError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(field, N)?);
        Ok(a)
    }

    pub fn u8(&mut self, field: &'static str) -> Result<u8, WireError> {
        Ok(self.array::<1>(field)?[0])
    }

    pub fn u16(&mut self, field: &'static str) -> Result<u16, WireError> {
        Ok(u16::from_le_bytes(self.array(field)?))
    }

    /// A zigzag varint (see [`Sink::zigzag`]).
    pub fn zigzag(&mut self, field: &'static str) -> Result<i64, WireError> {
        let v = self.varint(field)?;
        Ok((v >> 1) as i64 ^ -((v & 1) as i64))
    }

    pub fn f32(&mut self, field: &'static str) -> Result<f32, WireError> {
        Ok(f32::from_le_bytes(self.array(field)?))
    }

    /// A canonical LEB128 varint: at most 10 bytes, no redundant trailing zero groups,
    /// no bits beyond 64.
    pub fn varint(&mut self, field: &'static str) -> Result<u64, WireError> {
        let start = self.pos;
        let mut v = 0u64;
        for i in 0..10 {
            let b = self.u8(field).map_err(|e| match e {
                WireError::Truncated { .. } => WireError::Truncated {
                    field,
                    offset: start,
                    needed: i + 1,
                    available: i,
                },
                e => e,
            })?;
            if i == 9 && b > 1 {
                return Err(WireError::invalid(field, start, "varint overflows 64 bits"));
            }
            v |= u64::from(b & 0x7f) << (7 * i);
            if b & 0x80 == 0 {
                if b == 0 && i > 0 {
                    return Err(WireError::invalid(
                        field,
                        start,
                        "varint is not in its shortest form",
                    ));
                }
                return Ok(v);
            }
        }
        Err(WireError::invalid(
            field,
            start,
            "varint longer than 10 bytes",
        ))
    }

    /// A count of items, each at least `min_item_bytes` long: refused if above `max`
    /// or if the remaining bytes cannot hold that many items, so a caller may allocate
    /// `count` items without trusting the sender.
    pub fn count(
        &mut self,
        field: &'static str,
        max: usize,
        min_item_bytes: usize,
    ) -> Result<usize, WireError> {
        let offset = self.pos;
        let n = self.varint(field)?;
        if n > max as u64 {
            return Err(WireError::TooLong {
                field,
                offset,
                len: n,
                max: max as u64,
            });
        }
        let n = n as usize;
        let needed = n.saturating_mul(min_item_bytes);
        if needed > self.remaining() {
            return Err(WireError::Truncated {
                field,
                offset: self.pos,
                needed,
                available: self.remaining(),
            });
        }
        Ok(n)
    }

    /// Succeeds only if every byte was read.
    pub fn finish(&self) -> Result<(), WireError> {
        match self.remaining() {
            0 => Ok(()),
            count => Err(WireError::TrailingBytes { count }),
        }
    }
}

/// IEEE 754 binary16 bits of `x`, rounded to nearest, ties to even (overflow → ±∞).
pub fn f16_from_f32(x: f32) -> u16 {
    let b = x.to_bits();
    let sign = ((b >> 16) & 0x8000) as u16;
    let exp = ((b >> 23) & 0xff) as i32;
    let man = b & 0x7f_ffff;
    if exp == 0xff {
        return sign | 0x7c00 | if man != 0 { 0x200 } else { 0 };
    }
    let e = exp - 127 + 15;
    if e >= 0x1f {
        return sign | 0x7c00;
    }
    let (m, shift) = if e <= 0 {
        if e < -10 {
            return sign;
        }
        // Subnormal half: value = M · 2⁻²⁴.
        (man | 0x80_0000, (14 - e) as u32)
    } else {
        (((e as u32) << 23) | man, 13)
    };
    let half = 1u32 << (shift - 1);
    let rem = m & ((1 << shift) - 1);
    let mut r = m >> shift;
    if rem > half || (rem == half && r & 1 == 1) {
        // A carry out of the mantissa correctly bumps the exponent (up to ∞).
        r += 1;
    }
    sign | r as u16
}

/// The f32 value of IEEE 754 binary16 bits (exact: every half is an f32).
pub fn f32_from_f16(h: u16) -> f32 {
    let sign = u32::from(h & 0x8000) << 16;
    let e = u32::from((h >> 10) & 0x1f);
    let m = u32::from(h & 0x3ff);
    let bits = match e {
        0 => {
            let v = m as f32 * f32::from_bits(0x3380_0000); // 2⁻²⁴
            return if sign != 0 { -v } else { v };
        }
        31 => sign | 0x7f80_0000 | (m << 13),
        _ => sign | ((e + 112) << 23) | (m << 13),
    };
    f32::from_bits(bits)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_round_trips_every_value() {
        for h in 0..=u16::MAX {
            let f = f32_from_f16(h);
            if f.is_nan() {
                assert!(f16_from_f32(f) & 0x7c00 == 0x7c00 && f16_from_f32(f) & 0x3ff != 0);
            } else {
                assert_eq!(f16_from_f32(f), h, "half {h:#06x} = {f}");
            }
        }
        assert_eq!(f16_from_f32(1.0), 0x3c00);
        assert_eq!(f16_from_f32(65520.0), 0x7c00); // rounds to ∞
        assert_eq!(f16_from_f32(1.0 + 1.0 / 2048.0), 0x3c00); // tie → even
        assert_eq!(f16_from_f32(1.0 + 3.0 / 2048.0), 0x3c02);
        assert_eq!(f16_from_f32(1e-9), 0);
    }

    #[test]
    fn varints_are_canonical() {
        for v in [0, 1, 127, 128, 300, u32::MAX as u64, u64::MAX] {
            let mut b = Vec::new();
            b.varint(v);
            let mut c = Counter::default();
            c.varint(v);
            assert_eq!(b.len(), c.0);
            let mut r = Reader::new(&b);
            assert_eq!(r.varint("v").unwrap(), v);
            r.finish().unwrap();
        }
        assert!(Reader::new(&[0x80, 0x00]).varint("v").is_err());
        assert!(
            Reader::new(&[0xff; 9].iter().chain(&[2]).copied().collect::<Vec<_>>())
                .varint("v")
                .is_err()
        );
        assert!(matches!(
            Reader::new(&[0x80]).varint("v"),
            Err(WireError::Truncated { .. })
        ));
    }
}
