//! Compiles `mwb/v1/*.proto` with protox (pure Rust, no system `protoc`) and prost-build.
use protox::prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=mwb");
    let fds = protox::Compiler::new(["."])?
        .include_imports(true)
        .include_source_info(false)
        .open_files(["mwb/v1/mwb.proto"])?
        .file_descriptor_set();
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    // The descriptor set is also the schema record an MCAP recording embeds.
    std::fs::write(out.join("mwb_v1_descriptor.bin"), fds.encode_to_vec())?;
    prost_build::Config::new().compile_fds(fds)?;
    Ok(())
}
