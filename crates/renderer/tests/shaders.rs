//! Every WGSL file is listed in `shaders.rs`, each entry point's module and the composed render
//! module validate with naga, and the Rust uniform mirrors have the sizes the WGSL layout gives.

use lp3d_renderer::gpu_types::{DecoderUniform, DisplayUniform, Params};
use lp3d_renderer::settings::MAX_SAMPLES;
use lp3d_renderer::shaders;

fn parse() -> naga::Module {
    naga::front::wgsl::parse_str(&shaders::render_module_source()).expect("WGSL parses")
}

#[test]
fn every_wgsl_file_is_listed() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let mut on_disk: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".wgsl"))
        .collect();
    on_disk.sort();
    let mut listed: Vec<String> = shaders::STAGES.iter().map(|s| s.file.to_string()).collect();
    listed.sort();
    assert_eq!(on_disk, listed, "shaders/ and shaders.rs::STAGES disagree");
}

fn validate(module: &naga::Module) {
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::default())
        .validate(module)
        .expect("WGSL validates");
}

#[test]
fn render_module_validates() {
    let module = parse();
    validate(&module);
    for entry in [shaders::RENDER_ENTRY, shaders::DEPTH_BOUNDS_ENTRY, shaders::PRESENT_ENTRY] {
        assert!(module.entry_points.iter().any(|e| e.name == entry), "missing entry point {entry}");
    }
}

/// Each entry point's stage list is a module on its own: nothing it needs comes from a file
/// that only another entry point lists.
#[test]
fn each_entry_module_validates() {
    for entry in shaders::ENTRY_POINTS {
        let source = shaders::module_source(entry.stages);
        let module = naga::front::wgsl::parse_str(&source).unwrap_or_else(|e| panic!("{}: {e}", entry.name));
        validate(&module);
        let names: Vec<&str> = module.entry_points.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, [entry.name]);
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
