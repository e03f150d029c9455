//! The triplane file (`docs/triplane-format.md`): `Triplane::load` and `from_reader` (every
//! key, header and claimed size checked before data is read; no pickle), and `Triplane::save`
//! (atomic).

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use super::*;
use crate::npz::{NpyArray, NpyData};

impl Triplane {
    /// Loads a triplane `.npz` (never with pickle). Errors name the file and the key.
    ///
    /// Nothing the file claims is trusted before it is checked: the path must be a regular file
    /// (a FIFO, device or directory is an [`Error::Io`] at once, never a hang), the zip's entry
    /// sizes must fit the file and [`MAX_ENTRY_BYTES`](npz::MAX_ENTRY_BYTES), and every `.npy`
    /// header's dtype, shape and size must match the format (and its caps, [`FILE_LIMITS`])
    /// before any data is read. `lp3d.render.triplane_io.load_triplane` makes the same decisions.
    pub fn load(path: impl AsRef<Path>) -> Result<Triplane> {
        let path = path.as_ref();
        let (file, bytes) = open_regular_file(path, "a triplane .npz")?;
        Triplane::from_reader(BufReader::new(file), bytes, path)
    }

    /// [`Triplane::load`] from any reader of an `.npz` that is `bytes` long in all (the real size:
    /// every size the archive claims is checked against it); `path` names it in errors.
    pub fn from_reader<R: std::io::Read + std::io::Seek>(
        reader: R,
        bytes: u64,
        path: &Path,
    ) -> Result<Triplane> {
        let fmt = |field: &str, message: String| format_error(path, field, message);
        if bytes == 0 {
            return Err(fmt("", "empty file, not an .npz triplane".into()));
        }
        if bytes > MAX_FILE_BYTES {
            return Err(fmt(
                "",
                format!("{bytes} bytes, more than the cap of {MAX_FILE_BYTES} for a triplane file"),
            ));
        }
        let mut npz = npz::NpzReader::new(reader, bytes).map_err(|(k, m)| fmt(&k, m))?;
        let keys = checked_keys(&mut npz, path)?;
        let arrays = read_arrays(&mut npz, &keys, path)?;
        from_arrays(arrays, path)
    }

    /// Writes the triplane atomically ([`crate::atomic`]): a temporary file of this call's own in
    /// the same directory, synced, then renamed. Threads and processes may save one path at once
    /// (each publishes a whole file); on failure nothing is left behind and an existing file is
    /// untouched.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        self.validate()?;
        let path = path.as_ref();
        let planes = match self.plane_dtype {
            PlaneDtype::F32 => NpyData::F32(self.planes.clone()),
            PlaneDtype::F16 => {
                NpyData::F16(self.planes.iter().map(|&v| half::f16::from_f32(v).to_bits()).collect())
            }
        };
        let (d, b) = (&self.decoder, &self.bounds);
        let mut arrays: Vec<(&str, NpyArray)> = vec![
            ("planes", NpyArray { shape: vec![3, N_CHANNELS, self.height, self.width], data: planes }),
            ("decoder_w0", NpyArray::f32(vec![HIDDEN, N_CHANNELS], d.w0.clone())),
            ("decoder_b0", NpyArray::f32(vec![HIDDEN], d.b0.clone())),
            ("decoder_w1", NpyArray::f32(vec![N_OUT, HIDDEN], d.w1.clone())),
            ("decoder_b1", NpyArray::f32(vec![N_OUT], d.b1.clone())),
            ("box_warp", NpyArray { shape: vec![], data: NpyData::F64(vec![b.box_warp as f64]) }),
            ("ray_start", NpyArray { shape: vec![], data: NpyData::F64(vec![b.ray_start as f64]) }),
            ("ray_end", NpyArray { shape: vec![], data: NpyData::F64(vec![b.ray_end as f64]) }),
            ("format_version", NpyArray { shape: vec![], data: NpyData::I64(vec![FORMAT_VERSION]) }),
        ];
        if let Some(c) = &self.camera {
            arrays.push(("camera", NpyArray::f32(vec![25], c.0.to_vec())));
        }
        if let Some(o) = &self.occupancy {
            let g = o.resolution;
            arrays.push(("occupancy", NpyArray::f32(vec![g, g, g], o.bound.clone())));
            let crc = self.occupancy_checksum() as i64;
            arrays.push(("occupancy_checksum", NpyArray { shape: vec![], data: NpyData::I64(vec![crc]) }));
        }
        if let Some(s) = &self.source {
            // Write only what the readers accept (the format's caps).
            let n = s.chars().count();
            if n > MAX_SOURCE_CHARS {
                return Err(Error::invalid(
                    "source",
                    format!("{n} characters, more than the cap of {MAX_SOURCE_CHARS}"),
                ));
            }
            arrays.push(("source", NpyArray { shape: vec![], data: NpyData::Str(s.clone()) }));
        }
        crate::atomic::write_atomically(path, |file| npz::write_npz(file, &arrays))
    }
}

/// Keys a format-version-1 file must hold.
pub const REQUIRED_KEYS: [&str; 9] = [
    "planes",
    "decoder_w0",
    "decoder_b0",
    "decoder_w1",
    "decoder_b1",
    "box_warp",
    "ray_start",
    "ray_end",
    "format_version",
];
/// Keys it may hold besides (`occupancy` and `occupancy_checksum` only together).
pub const OPTIONAL_KEYS: [&str; 4] = ["camera", "occupancy", "occupancy_checksum", "source"];

/// Opens `path` for reading and checks that it is a regular file (`what` names the file it should
/// be, in the error), returning it and its size. Opened non-blocking: a FIFO would otherwise wait
/// for a writer forever (and a blocked open ignores Ctrl-C); for a regular file the flag changes
/// nothing.
pub(crate) fn open_regular_file(path: &Path, what: &str) -> Result<(File, u64)> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY);
    }
    let file = options.open(path).map_err(|e| Error::io(path, e))?;
    let meta = file.metadata().map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        let kind =
            if meta.is_dir() { std::io::ErrorKind::IsADirectory } else { std::io::ErrorKind::InvalidInput };
        let message = format!("{}, not a regular file ({what})", file_kind(&meta.file_type()));
        return Err(Error::io_kind(path, kind, message));
    }
    Ok((file, meta.len()))
}

/// What a non-regular file is, for the error message.
fn file_kind(t: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "is a FIFO (named pipe)";
        }
        if t.is_char_device() {
            return "is a character device";
        }
        if t.is_block_device() {
            return "is a block device";
        }
        if t.is_socket() {
            return "is a socket";
        }
    }
    if t.is_dir() {
        "is a directory"
    } else {
        "is not a regular file"
    }
}

/// The key of the format version, read before anything else.
const VERSION: &str = "format_version";

/// A [`Error::Format`] about `field` of the file at `path`.
pub(crate) fn format_error(path: &Path, field: &str, message: String) -> Error {
    Error::Format { path: path.into(), field: field.into(), message }
}

/// The archive's keys, sorted, after the checks that need no data but the version: the version
/// is supported, no key is unknown, none required is missing, and `occupancy` comes with its
/// checksum.
fn checked_keys<R: std::io::Read + std::io::Seek>(
    npz: &mut npz::NpzReader<R>,
    path: &Path,
) -> Result<Vec<String>> {
    let fmt = |field: &str, message: String| format_error(path, field, message);
    let mut keys: Vec<String> = npz.keys().map(str::to_string).collect();
    keys.sort();
    let has = |k: &str| keys.iter().any(|x| x == k);

    // The version first, so a newer file is reported as such rather than by its new keys.
    if !has(VERSION) {
        return Err(fmt(VERSION, "missing key (not an lp3d triplane file?)".into()));
    }
    let header = npz.header(VERSION).map_err(|m| fmt(VERSION, m))?;
    check_header(VERSION, &header).map_err(|m| fmt(VERSION, m))?;
    let version = match npz.read(VERSION, &header).map_err(|m| fmt(VERSION, m))? {
        NpyData::I64(v) => v[0],
        NpyData::I32(v) => v[0] as i64,
        _ => unreachable!("check_header admits integers only"),
    };
    if version != FORMAT_VERSION {
        return Err(fmt(
            VERSION,
            format!("unknown format_version {version} (this reader supports {FORMAT_VERSION})"),
        ));
    }
    let unknown: Vec<&String> = keys
        .iter()
        .filter(|k| !REQUIRED_KEYS.contains(&k.as_str()) && !OPTIONAL_KEYS.contains(&k.as_str()))
        .collect();
    if let Some(first) = unknown.first() {
        return Err(fmt(first, format!("unknown key(s) {unknown:?} (format_version {FORMAT_VERSION})")));
    }
    let missing: Vec<&str> = {
        let mut m: Vec<&str> = REQUIRED_KEYS.iter().copied().filter(|k| !has(k)).collect();
        m.sort();
        m
    };
    if let Some(first) = missing.first() {
        return Err(fmt(first, format!("missing required key(s) {missing:?}")));
    }
    if has("occupancy") != has("occupancy_checksum") {
        let absent = if has("occupancy") { "occupancy_checksum" } else { "occupancy" };
        return Err(fmt(absent, "missing ('occupancy' and 'occupancy_checksum' go together)".into()));
    }
    Ok(keys)
}

/// Every array but the version, read after all headers passed `check_header`: no size an
/// archive claims reaches the allocator unchecked.
fn read_arrays<R: std::io::Read + std::io::Seek>(
    npz: &mut npz::NpzReader<R>,
    keys: &[String],
    path: &Path,
) -> Result<Vec<(String, NpyArray)>> {
    let fmt = |field: &str, message: String| format_error(path, field, message);
    // Every header against the format before any data is read: no claim reaches the allocator.
    let mut headers = Vec::with_capacity(keys.len());
    for key in keys.iter().filter(|k| *k != VERSION) {
        let h = npz.header(key).map_err(|m| fmt(key, m))?;
        check_header(key, &h).map_err(|m| fmt(key, m))?;
        headers.push((key.clone(), h));
    }
    let mut arrays: Vec<(String, NpyArray)> = Vec::with_capacity(headers.len());
    for (key, h) in headers {
        let data = npz.read(&key, &h).map_err(|m| fmt(&key, m))?;
        arrays.push((key, NpyArray { shape: h.shape, data }));
    }
    Ok(arrays)
}

/// The triplane from its checked arrays (as [`read_arrays`] returns them), validated; a stored
/// occupancy checksum must match these planes and decoder.
fn from_arrays(mut arrays: Vec<(String, NpyArray)>, path: &Path) -> Result<Triplane> {
    let fmt = |field: &str, message: String| format_error(path, field, message);
    let mut take = |key: &str| {
        let i = arrays.iter().position(|(k, _)| k == key)?;
        Some(arrays.swap_remove(i).1)
    };

    let planes = take("planes").expect("required key present");
    let (height, width) = (planes.shape[2], planes.shape[3]);
    let (planes, plane_dtype) = match planes.data {
        NpyData::F16(v) => (v.iter().map(|&b| half::f16::from_bits(b).to_f32()).collect(), PlaneDtype::F16),
        NpyData::F32(v) => (v, PlaneDtype::F32),
        _ => unreachable!("check_header admits float16 and float32 planes only"),
    };
    let mut floats = |key: &str| take(key).and_then(|a| a.to_f32()).expect("required float key present");
    let decoder = Decoder {
        w0: floats("decoder_w0"),
        b0: floats("decoder_b0"),
        w1: floats("decoder_w1"),
        b1: floats("decoder_b1"),
    };
    let mut scalar = |key: &str| take(key).and_then(|a| a.scalar_f64()).expect("required scalar present");
    let bounds = SceneBounds::new(scalar("box_warp"), scalar("ray_start"), scalar("ray_end")).map_err(
        |e| match e {
            Error::InvalidInput { field, message } => fmt(&field, message),
            other => other,
        },
    )?;
    let camera = match take("camera") {
        None => None,
        Some(a) => {
            let v64: Vec<f64> = match a.data {
                NpyData::F64(v) => v,
                NpyData::F32(v) => v.iter().map(|&x| x as f64).collect(),
                _ => unreachable!("check_header admits float32 and float64 cameras only"),
            };
            let camera = Camera::from_label(&v64, "camera").map_err(|e| fmt("camera", e.to_string()))?;
            if let Some(i) = v64.iter().position(|&x| !(x as f32).is_finite()) {
                return Err(fmt("camera", format!("value {} at index {i} is not finite as float32", v64[i])));
            }
            Some(camera)
        }
    };
    let checksum = match take("occupancy_checksum").map(|a| a.data) {
        None => None,
        Some(NpyData::I64(v)) => Some(v[0]),
        Some(NpyData::I32(v)) => Some(v[0] as i64),
        Some(_) => unreachable!("check_header admits integer checksums only"),
    };
    let occupancy = match take("occupancy") {
        None => None,
        Some(NpyArray { shape, data: NpyData::F32(bound) }) => {
            Some(Occupancy { resolution: shape[0], bound })
        }
        Some(_) => unreachable!("check_header admits float32 grids only"),
    };
    let source = match take("source").map(|a| a.data) {
        None => None,
        Some(NpyData::Str(s)) => Some(s),
        Some(_) => unreachable!("check_header admits unicode sources only"),
    };
    let tri = Triplane { planes, height, width, plane_dtype, decoder, bounds, camera, occupancy, source };
    tri.validate().map_err(|e| match e {
        Error::InvalidInput { field, message } => fmt(key_of_field(&field), message),
        other => other,
    })?;
    if let Some(stored) = checksum {
        let actual = tri.occupancy_checksum() as i64;
        if stored != actual {
            return Err(fmt(
                "occupancy_checksum",
                format!(
                    "{stored} does not match these planes and decoder ({actual}): the grid was baked \
                     for another triplane; bake it again"
                ),
            ));
        }
    }
    Ok(tri)
}

/// Checks one entry's `.npy` header (dtype, shape, caps) against the format's table before any
/// of its data is read. `lp3d.render.triplane_io` holds the same table.
fn check_header(key: &str, h: &npz::NpyHeader) -> std::result::Result<(), String> {
    use npz::Dtype::{F16, F32, F64, I32, I64};
    const REAL: &[npz::Dtype] = &[F16, F32, F64, I32, I64];
    let shape = h.shape.as_slice();
    let (dtypes, want): (&[npz::Dtype], Option<&[usize]>) = match key {
        "planes" => (&[F16, F32], None),
        "decoder_w0" => (&[F32, F64], Some(&[HIDDEN, N_CHANNELS])),
        "decoder_b0" => (&[F32, F64], Some(&[HIDDEN])),
        "decoder_w1" => (&[F32, F64], Some(&[N_OUT, HIDDEN])),
        "decoder_b1" => (&[F32, F64], Some(&[N_OUT])),
        "box_warp" | "ray_start" | "ray_end" => (REAL, Some(&[])),
        "format_version" | "occupancy_checksum" => (&[I32, I64], Some(&[])),
        "camera" => (&[F32, F64], Some(&[25])),
        "occupancy" => (&[F32], None),
        "source" => {
            return match h.dtype {
                npz::Dtype::Unicode(n) if n <= MAX_SOURCE_CHARS => Ok(()),
                npz::Dtype::Unicode(n) => {
                    Err(format!("a string of {n} characters, more than the cap of {MAX_SOURCE_CHARS}"))
                }
                d => Err(format!("dtype must be a unicode string (<U…), got {}", d.name())),
            }
        }
        _ => return Ok(()),
    };
    if !dtypes.contains(&h.dtype) {
        let names: Vec<String> = dtypes.iter().map(|d| d.name()).collect();
        return Err(format!("dtype must be {}, got {}", names.join(" or "), h.dtype.name()));
    }
    let got = h.shape_text();
    match (key, want) {
        (_, Some(want)) if shape != want => {
            Err(format!("shape must be {}, got {got}", npz::shape_text(want)))
        }
        ("planes", _) => {
            if shape.len() != 4 || shape[0] != 3 || shape[1] != N_CHANNELS {
                return Err(format!("shape must be (3, {N_CHANNELS}, H, W), got {got}"));
            }
            let (height, width) = (shape[2], shape[3]);
            if !(2..=MAX_PLANE_SIZE).contains(&height) || !(2..=MAX_PLANE_SIZE).contains(&width) {
                return Err(format!("H and W must be in [2, {MAX_PLANE_SIZE}], got {height}x{width}"));
            }
            Ok(())
        }
        ("occupancy", _) => {
            if shape.len() != 3 || shape[1] != shape[0] || shape[2] != shape[0] {
                return Err(format!("shape must be (G, G, G), got {got}"));
            }
            if !(1..=MAX_OCCUPANCY_RESOLUTION).contains(&shape[0]) {
                return Err(format!("G must be in [1, {MAX_OCCUPANCY_RESOLUTION}], got G = {}", shape[0]));
            }
            Ok(())
        }
        _ => Ok(()),
    }
}

/// The file key of a [`Triplane::validate`] field (`w0` is stored as `decoder_w0`).
fn key_of_field(field: &str) -> &str {
    match field {
        "w0" => "decoder_w0",
        "b0" => "decoder_b0",
        "w1" => "decoder_w1",
        "b1" => "decoder_b1",
        f => f,
    }
}
