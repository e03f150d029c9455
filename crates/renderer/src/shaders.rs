//! The one place WGSL enters the crate. WGSL has no includes, so the render module is the
//! concatenation of the stage files in `shaders/`, in dependency order.

/// The stage files, in the order they are concatenated. A test fails if a `.wgsl` file in
/// `shaders/` is missing from this list.
pub const SOURCES: [(&str, &str); 8] = [
    ("params.wgsl", include_str!("../../../shaders/params.wgsl")),
    ("camera.wgsl", include_str!("../../../shaders/camera.wgsl")),
    ("sampling.wgsl", include_str!("../../../shaders/sampling.wgsl")),
    ("triplane.wgsl", include_str!("../../../shaders/triplane.wgsl")),
    ("decoder.wgsl", include_str!("../../../shaders/decoder.wgsl")),
    ("march.wgsl", include_str!("../../../shaders/march.wgsl")),
    ("render.wgsl", include_str!("../../../shaders/render.wgsl")),
    ("present.wgsl", include_str!("../../../shaders/present.wgsl")),
];

/// Entry points of the render module.
pub const RENDER_ENTRY: &str = "render_rays";
pub const DEPTH_BOUNDS_ENTRY: &str = "depth_bounds_pass";
pub const PRESENT_ENTRY: &str = "present";

/// The full WGSL source of the render module.
pub fn render_module_source() -> String {
    SOURCES.iter().map(|(_, s)| *s).collect::<Vec<_>>().join("\n")
}
