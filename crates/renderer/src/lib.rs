//! lp3d's triplane renderer: EG3D's volume rendering of triplanes, exactly, in WGSL compute
//! shaders on wgpu. It knows nothing about Python or egui: `crates/pybind` and the viewer
//! borrow it.
//!
//! Modules, in the order of the data flow:
//!
//! - [`camera`]: 25-float EG3D camera labels, their validation, and the look-at camera.
//! - [`triplane`]: planes + decoder, the plane-axis convention and the scene bounds.
//! - [`npz`]: the strict `.npz`/`.npy` reader and writer under the triplane file.
//! - [`settings`]: how to render (EG3D's `rendering_kwargs`).
//! - [`occupancy`]: the grid of density bounds that lets the kernel skip empty space.
//! - [`baked`]: the baked field, the decoder's output stored on a fine grid and looked up.
//! - [`shaders`]: the WGSL stage files and the entry points' modules made of them.
//! - [`gpu_types`]: the plain-old-data mirrors of the WGSL uniforms.
//! - [`kernel`]: the fast and quick forms of the render kernel and which one a renderer uses.
//! - [`device`]: the wgpu device, created headless or borrowed from the viewer.
//! - [`renderer`]: GPU pipelines and dispatch.
//! - [`superres`]: EG3D's super-resolution network (folded) on the feature image, after the render.
//!
//! Beside them: [`error`] (the crate's one error type) and [`atomic`] (atomic file writes).

pub mod atomic;
pub mod baked;
pub mod camera;
pub mod device;
pub mod error;
pub mod gpu_types;
pub mod kernel;
pub mod npz;
pub mod occupancy;
pub mod renderer;
pub mod settings;
pub mod shaders;
pub mod superres;
pub mod triplane;

pub use baked::BakeSpec;
pub use camera::Camera;
pub use device::GpuContext;
pub use error::{Error, Result};
pub use kernel::{Kernel, KernelChoice};
pub use occupancy::Occupancy;
pub use renderer::{GpuBaked, GpuTriplane, RenderOutput, Renderer, DISPLAY_FORMAT};
pub use settings::{Display, Outputs, RenderSettings, Skips};
pub use superres::{SuperRes, SuperresBlock, SuperresKernels, SuperresWeights};
pub use triplane::{Decoder, PlaneDtype, SceneBounds, SceneInfo, Triplane};
