//! Any bytes: decoding never panics, and a message that decodes re-encodes to exactly
//! the input (the encoding is canonical) with `encoded_len` equal to its length.
#![no_main]

use doorslam_ipc::wire::Message;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = Message::decode(data) {
        let b = m.encode().expect("a decoded message encodes");
        assert_eq!(b, data);
        assert_eq!(m.encoded_len(), data.len());
    }
});
