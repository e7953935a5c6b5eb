//! Each kind's body decoder directly: the first input byte picks the kind, a valid header
//! of that kind is put in front of the rest, so the fuzzer spends no time finding the
//! header. Same checks as `decode`.
#![no_main]

use doorslam_ipc::wire::{Kind, Message, WIRE_VERSION};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&k, body)) = data.split_first() else {
        return;
    };
    let kind = Kind::ALL[usize::from(k) % Kind::ALL.len()];
    // version, kind, sender "fz", epoch 1, sequence 0
    let mut bytes = vec![WIRE_VERSION, kind as u8, 2, b'f', b'z', 1, 0];
    bytes.extend_from_slice(body);
    if let Ok(m) = Message::decode(&bytes) {
        assert_eq!(m.kind(), kind);
        assert_eq!(m.encode().expect("a decoded message encodes"), bytes);
        assert_eq!(m.encoded_len(), bytes.len());
    }
});
