//! The two forms of the render kernel and which of them a `Renderer` uses: the fast
//! (unrolled) kernel, the quick (rolled) one, and on lavapipe the background compile that
//! swaps the fast one in once Mesa's shader cache holds it (the compile itself is
//! `renderer/background.rs`).

use crate::error::{Error, Result};
use crate::shaders;

/// The two compiled forms of the render kernel (`shaders/decoder.wgsl`, picked by the override
/// constant `ROLLED_DECODER`). They do the same arithmetic in the same order, so their outputs
/// are bit-identical (a test checks); only the time to compile and to run differs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kernel {
    /// Unrolled decoder: the fastest to run, and the slowest to compile the first time on lavapipe
    /// (docs/performance.md, "First image").
    Fast,
    /// Rolled decoder: compiles many times faster on lavapipe and runs slower there.
    Quick,
}

/// Which kernels a `Renderer` builds. `Renderer::new` reads it from the `LP3D_KERNEL`
/// environment variable (`auto`, `fast` or `quick`; unset = `auto`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KernelChoice {
    /// On a CPU adapter (lavapipe, where a compile takes tens of seconds): draw with the quick
    /// kernel at once while the fast one compiles on a background thread (on its own device,
    /// so the compile never blocks this device's queue), and switch to it when it is ready;
    /// Mesa's shader cache keeps both for later processes. Once a fast kernel has been
    /// compiled into the cache folder `MESA_SHADER_CACHE_DIR` names (a marker file there
    /// records it), later processes start with the fast kernel at once. On other adapters:
    /// `Fast`.
    Auto,
    /// The quick kernel at once and the fast one from a background compile, on any adapter
    /// and whatever the marker says (what `Auto` does on a CPU adapter the first time).
    QuickThenFast,
    /// The fast kernel only (its first use waits for its compile).
    Fast,
    /// The quick kernel only.
    Quick,
}

impl KernelChoice {
    /// `LP3D_KERNEL` as a choice (`parse`).
    pub fn from_env() -> Result<KernelChoice> {
        KernelChoice::parse(std::env::var("LP3D_KERNEL").ok().as_deref())
    }

    /// Whether the fast kernel compiles on a background thread while the quick one serves:
    /// always for `QuickThenFast`; for `Auto` on a CPU adapter until the fast kernel has been
    /// compiled once (`marker` exists).
    pub(crate) fn compiles_in_background(
        self,
        adapter: &wgpu::AdapterInfo,
        marker: Option<&std::path::Path>,
    ) -> bool {
        match self {
            KernelChoice::QuickThenFast => true,
            KernelChoice::Auto => {
                adapter.device_type == wgpu::DeviceType::Cpu && !marker.is_some_and(|m| m.exists())
            }
            KernelChoice::Fast | KernelChoice::Quick => false,
        }
    }

    /// `auto`, `fast` or `quick`; unset or empty = `auto`. Anything else is an error naming
    /// `LP3D_KERNEL`.
    pub fn parse(value: Option<&str>) -> Result<KernelChoice> {
        match value {
            None | Some("") | Some("auto") => Ok(KernelChoice::Auto),
            Some("fast") => Ok(KernelChoice::Fast),
            Some("quick") => Ok(KernelChoice::Quick),
            Some(other) => {
                Err(Error::invalid("LP3D_KERNEL", format!("must be auto, fast or quick, got {other:?}")))
            }
        }
    }
}

/// How render_rays uses a baked field (`shaders/baked.wgsl`'s override constant `BAKED`): not at
/// all (exact mode and its skips), or in place of the decoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FieldUse {
    None,
    Lookup,
}

/// render_rays specialised for `kernel`.
pub(crate) fn build_render_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::PipelineLayout,
    kernel: Kernel,
) -> wgpu::ComputePipeline {
    build_render_variant(device, module, layout, kernel, FieldUse::None)
}

/// render_rays specialised for `kernel` and a use of the baked field.
pub(crate) fn build_render_variant(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::PipelineLayout,
    kernel: Kernel,
    field: FieldUse,
) -> wgpu::ComputePipeline {
    let rolled = match kernel {
        Kernel::Fast => 0.0,
        Kernel::Quick => 1.0,
    };
    let (label, flag) = match (field, kernel) {
        (FieldUse::None, Kernel::Fast) => ("lp3d render_rays (fast kernel)", None),
        (FieldUse::None, Kernel::Quick) => ("lp3d render_rays (quick kernel)", None),
        (FieldUse::Lookup, _) => ("lp3d render_rays (baked)", Some("BAKED")),
    };
    let mut constants = vec![("ROLLED_DECODER", rolled)];
    constants.extend(flag.map(|f| (f, 1.0)));
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: Some(layout),
        module,
        entry_point: Some(shaders::RENDER_ENTRY),
        compilation_options: wgpu::PipelineCompilationOptions { constants: &constants, ..Default::default() },
        cache: None,
    })
}

/// The marker file that says this adapter's Mesa shader cache holds this build's fast kernel and
/// the bake kernel with its decoder: `$MESA_SHADER_CACHE_DIR/lp3d-kernels/fast-<hash>`, the hash
/// over the WGSL source, the pipelines the background compile leaves cached, and the adapter and
/// driver. `None` without `MESA_SHADER_CACHE_DIR` or with Mesa's cache disabled (no
/// marker: `Auto` then always starts with the quick kernel). Kept inside Mesa's folder so that
/// clearing the cache clears the marker too.
pub(crate) fn fast_kernel_marker(info: &wgpu::AdapterInfo) -> Option<std::path::PathBuf> {
    use std::hash::{Hash, Hasher};
    let disabled = std::env::var("MESA_SHADER_CACHE_DISABLE")
        .is_ok_and(|v| matches!(v.to_ascii_lowercase().as_str(), "1" | "true" | "yes"));
    let dir = std::env::var_os("MESA_SHADER_CACHE_DIR").filter(|d| !d.is_empty())?;
    if disabled {
        return None;
    }
    // FNV-1a: stable across Rust versions, unlike std's default hasher.
    struct Fnv(u64);
    impl Hasher for Fnv {
        fn finish(&self) -> u64 {
            self.0
        }
        fn write(&mut self, bytes: &[u8]) {
            for b in bytes {
                self.0 = (self.0 ^ *b as u64).wrapping_mul(0x100000001b3);
            }
        }
    }
    let mut h = Fnv(0xcbf29ce484222325);
    shaders::render_module_source().hash(&mut h);
    // Markers written before the background compile also compiled the bake kernel do not count.
    "render_rays + bake_field".hash(&mut h);
    (&info.name, &info.driver, &info.driver_info, info.vendor, info.device).hash(&mut h);
    Some(std::path::Path::new(&dir).join("lp3d-kernels").join(format!("fast-{:016x}", h.finish())))
}

/// Writes an empty marker file (best effort: a failure only costs later processes the quick
/// start).
pub(crate) fn write_marker(path: &std::path::Path) {
    if let Some(dir) = path.parent() {
        if std::fs::create_dir_all(dir).is_ok() {
            let _ = crate::atomic::write_atomically(path, |_| Ok(()));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernel_choice_parses_lp3d_kernel() {
        assert_eq!(KernelChoice::parse(None).unwrap(), KernelChoice::Auto);
        assert_eq!(KernelChoice::parse(Some("")).unwrap(), KernelChoice::Auto);
        assert_eq!(KernelChoice::parse(Some("auto")).unwrap(), KernelChoice::Auto);
        assert_eq!(KernelChoice::parse(Some("fast")).unwrap(), KernelChoice::Fast);
        assert_eq!(KernelChoice::parse(Some("quick")).unwrap(), KernelChoice::Quick);
        let e = KernelChoice::parse(Some("Fast")).unwrap_err().to_string();
        assert!(e.starts_with("LP3D_KERNEL:") && e.contains("auto, fast or quick"), "{e}");
    }
}
