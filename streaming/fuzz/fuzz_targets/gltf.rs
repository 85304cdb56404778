#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| rtstream_streaming::fuzz::gltf(data));
