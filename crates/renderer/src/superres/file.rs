//! A model package's super-resolution weights file, `MODEL.superres.npz`
//! (`docs/model-package.md`): the folded network as plain float32 arrays, so that the viewer, the
//! Python module and the share page read one network without ONNX or PyTorch. Written by
//! `lp3d.lift.superres_weights` beside the package's `MODEL.superres.onnx`; read here, every
//! header checked before data is read (the bounded reader of `crate::npz`), then
//! [`SuperresWeights::validate`].
//!
//! Keys: `format_version` (int, 1), `input_resolution` (int), and per ×2 block `i` the six
//! arrays of [`WEIGHTS_PARTS`] as `convs_up_0`, `biases_up_0`, ...

use std::io::BufReader;
use std::path::Path;

use super::{SuperresBlock, SuperresWeights, MAX_OUTPUT_RESOLUTION};
use crate::error::Result;
use crate::npz::{NpyData, NpzReader, MAX_ENTRIES};
use crate::triplane::{format_error, open_regular_file};

/// The version of the weights file this reader knows.
pub const WEIGHTS_FORMAT_VERSION: i64 = 1;
/// The folded network's tensors, one per block each (`FoldedSuperResolution`'s names).
pub const WEIGHTS_PARTS: [&str; 6] =
    ["convs_up", "biases_up", "convs", "biases", "rgb_weights", "rgb_biases"];
/// Largest weights file accepted (EG3D's widest SR, 8× from 128², is about 40 MB).
const MAX_WEIGHTS_BYTES: u64 = 512 << 20;

impl SuperresWeights {
    /// Reads and validates a weights file; errors name the file and the key.
    // Long because: each key is checked (present, dtype, shape) before its data is read, in the
    // file's order; the checks share the reader and the widths read so far.
    pub fn load(path: impl AsRef<Path>) -> Result<SuperresWeights> {
        let path = path.as_ref();
        let fmt = |field: &str, message: String| format_error(path, field, message);
        let (file, bytes) = open_regular_file(path, "a super-resolution weights .npz")?;
        if bytes == 0 || bytes > MAX_WEIGHTS_BYTES {
            return Err(fmt("", format!("{bytes} bytes: a weights file holds 1 to {MAX_WEIGHTS_BYTES}")));
        }
        let mut npz = NpzReader::new(BufReader::new(file), bytes).map_err(|(k, m)| fmt(&k, m))?;
        let keys: Vec<String> = npz.keys().map(str::to_owned).collect();
        let mut int = |key: &str| -> Result<i64> {
            if !keys.iter().any(|k| k == key) {
                return Err(fmt(key, "missing".into()));
            }
            let header = npz.header(key).map_err(|m| fmt(key, m))?;
            match npz.read(key, &header).map_err(|m| fmt(key, m))? {
                NpyData::I64(v) if header.shape.is_empty() => Ok(v[0]),
                NpyData::I32(v) if header.shape.is_empty() => Ok(v[0] as i64),
                _ => Err(fmt(key, format!("must be an integer scalar, got shape {:?}", header.shape))),
            }
        };
        let version = int("format_version")?;
        if version != WEIGHTS_FORMAT_VERSION {
            return Err(fmt(
                "format_version",
                format!("{version} is not a version this reader knows ({WEIGHTS_FORMAT_VERSION})"),
            ));
        }
        let r = int("input_resolution")?;
        if !(1..=MAX_OUTPUT_RESOLUTION as i64 / 2).contains(&r) {
            return Err(fmt("input_resolution", format!("{r} is not in [1, {}]", MAX_OUTPUT_RESOLUTION / 2)));
        }
        let n_blocks = keys.iter().filter(|k| k.starts_with("convs_up_")).count();
        let expected = 2 + WEIGHTS_PARTS.len() * n_blocks;
        if n_blocks == 0 || keys.len() != expected || expected > MAX_ENTRIES {
            return Err(fmt(
                "",
                format!(
                    "expected format_version, input_resolution and the six arrays of each ×2 block \
                     ({}_0, ...), got keys {keys:?}",
                    WEIGHTS_PARTS[0]
                ),
            ));
        }
        let mut blocks = Vec::with_capacity(n_blocks);
        let mut in_channels = 0;
        for i in 0..n_blocks {
            let mut parts: Vec<(Vec<usize>, Vec<f32>)> = Vec::with_capacity(WEIGHTS_PARTS.len());
            for part in WEIGHTS_PARTS {
                let key = format!("{part}_{i}");
                if !keys.contains(&key) {
                    return Err(fmt(&key, "missing".into()));
                }
                let header = npz.header(&key).map_err(|m| fmt(&key, m))?;
                let values = match npz.read(&key, &header).map_err(|m| fmt(&key, m))? {
                    NpyData::F32(v) => v,
                    _ => return Err(fmt(&key, format!("must be float32, got {}", header.dtype.name()))),
                };
                parts.push((header.shape, values));
            }
            let c = parts[0].0.first().copied().unwrap_or(0);
            let cin = if i == 0 { parts[0].0.get(1).copied().unwrap_or(0) } else { blocks_width(&blocks) };
            if i == 0 {
                in_channels = cin;
            }
            let want: [Vec<usize>; 6] =
                [vec![c, cin, 3, 3], vec![c], vec![c, c, 3, 3], vec![c], vec![3, c, 1, 1], vec![3]];
            for ((part, (shape, _)), want) in WEIGHTS_PARTS.iter().zip(&parts).zip(&want) {
                if shape != want {
                    return Err(fmt(
                        &format!("{part}_{i}"),
                        format!("shape must be {want:?}, got {shape:?}"),
                    ));
                }
            }
            let mut values = parts.into_iter().map(|(_, v)| v);
            let mut next = || values.next().expect("six parts were read");
            blocks.push(SuperresBlock {
                channels: c,
                conv_up: next(),
                bias_up: next(),
                conv: next(),
                bias: next(),
                rgb_weight: next(),
                rgb_bias: next(),
            });
        }
        let weights = SuperresWeights { in_channels, input_resolution: r as usize, blocks };
        weights.validate().map_err(|e| fmt("", e.to_string()))?;
        Ok(weights)
    }
}

/// The width of the last block read (the next block's input channels).
fn blocks_width(blocks: &[SuperresBlock]) -> usize {
    blocks.last().map_or(0, |b| b.channels)
}
