//! lp3d's triplane renderer: EG3D's volume rendering of triplanes, exactly, in WGSL compute
//! shaders on wgpu. It knows nothing about Python or egui: `crates/pybind` and the viewer
//! borrow it.
//!
//! Modules follow the data flow: [`camera`] (25-float EG3D labels → rays), [`triplane`]
//! (planes + decoder, the plane-axis convention), [`settings`] (how to render), [`renderer`]
//! (GPU pipelines and dispatch), [`npz`] (the `.npz` triplane file).

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
pub mod triplane;

pub use baked::BakeSpec;
pub use camera::Camera;
pub use device::GpuContext;
pub use error::{Error, Result};
pub use kernel::{Kernel, KernelChoice};
pub use occupancy::Occupancy;
pub use renderer::{GpuBaked, GpuTriplane, RenderOutput, Renderer, DISPLAY_FORMAT};
pub use settings::{Display, Outputs, RenderSettings, Skips};
pub use triplane::{Decoder, PlaneDtype, SceneBounds, SceneInfo, Triplane};
