//! Compiles the recording wrappers (`proto/mwb/record/v1/record.proto`) into a descriptor set
//! of that one file; at run time it is appended to `mwb_proto::DESCRIPTOR_SET`, so a schema
//! record holds `mwb.v1` and the wrappers together. No Rust types are generated: the wrappers
//! are read and written with a hand-declared prost struct of the same wire shape.
use protox::prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    println!("cargo:rerun-if-changed=../proto/mwb");
    let fds = protox::Compiler::new(["proto", "../proto"])?
        .include_imports(false)
        .include_source_info(false)
        .open_files(["mwb/record/v1/record.proto"])?
        .file_descriptor_set();
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out.join("mwb_record_v1_descriptor.bin"),
        fds.encode_to_vec(),
    )?;
    Ok(())
}
