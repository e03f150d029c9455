//! Every WGSL file is listed in `shaders.rs`, the composed module validates with naga, and
//! the Rust uniform mirrors have the sizes the WGSL layout gives.

use lp3d_renderer::gpu_types::{DecoderUniform, DisplayUniform, Params};
use lp3d_renderer::settings::MAX_SAMPLES;
use lp3d_renderer::shaders;

fn parse() -> naga::Module {
    naga::front::wgsl::parse_str(&shaders::render_module_source()).expect("WGSL parses")
}

#[test]
fn every_wgsl_file_is_listed() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders");
    let mut on_disk: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".wgsl"))
        .collect();
    on_disk.sort();
    let mut listed: Vec<String> = shaders::SOURCES.iter().map(|(n, _)| n.to_string()).collect();
    listed.sort();
    assert_eq!(on_disk, listed, "shaders/ and shaders.rs::SOURCES disagree");
}

#[test]
fn render_module_validates() {
    let module = parse();
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::default())
        .validate(&module)
        .expect("WGSL validates");
    for entry in [shaders::RENDER_ENTRY, shaders::DEPTH_BOUNDS_ENTRY, shaders::PRESENT_ENTRY] {
        assert!(module.entry_points.iter().any(|e| e.name == entry), "missing entry point {entry}");
    }
}

#[test]
fn uniform_layouts_match_wgsl() {
    let module = parse();
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).unwrap();
    let size_of = |name: &str| {
        let (handle, _) = module.types.iter().find(|(_, t)| t.name.as_deref() == Some(name)).unwrap();
        layouter[handle].size as usize
    };
    assert_eq!(size_of("Params"), std::mem::size_of::<Params>());
    assert_eq!(size_of("Decoder"), std::mem::size_of::<DecoderUniform>());
    assert_eq!(size_of("Display"), std::mem::size_of::<DisplayUniform>());
    let max_samples = module
        .constants
        .iter()
        .find(|(_, c)| c.name.as_deref() == Some("MAX_SAMPLES"))
        .map(|(_, c)| match module.global_expressions[c.init] {
            naga::Expression::Literal(naga::Literal::U32(v)) => v,
            ref e => panic!("MAX_SAMPLES is not a u32 literal: {e:?}"),
        })
        .unwrap();
    assert_eq!(max_samples, MAX_SAMPLES);
}
