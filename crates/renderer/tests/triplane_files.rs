//! The triplane reader against hostile files: non-regular paths, size claims that must be
//! refused before anything is allocated, and a bounded, seeded mutation fuzzer asserting that
//! every mutated file loads or gives an error, never a panic or an abort. The Python side of the
//! same cases, and the check that both readers agree, is `tests/render/test_triplane_files.py`.

use std::io::Cursor;
use std::path::Path;

use lp3d_renderer::npz::{self, NpyArray, NpyData};
use lp3d_renderer::{Error, Triplane};

/// The arrays of a small valid triplane file.
fn good_arrays() -> Vec<(&'static str, NpyArray)> {
    let mut seed = 7u64;
    let mut noise = |n: usize| -> Vec<f32> {
        (0..n).map(|_| (xorshift(&mut seed) % 2001) as f32 / 1000.0 - 1.0).collect()
    };
    let scalar = |v: f64| NpyArray { shape: vec![], data: NpyData::F64(vec![v]) };
    vec![
        ("planes", NpyArray::f32(vec![3, 32, 6, 7], noise(3 * 32 * 6 * 7))),
        ("decoder_w0", NpyArray::f32(vec![64, 32], noise(64 * 32))),
        ("decoder_b0", NpyArray::f32(vec![64], noise(64))),
        ("decoder_w1", NpyArray::f32(vec![33, 64], noise(33 * 64))),
        ("decoder_b1", NpyArray::f32(vec![33], noise(33))),
        ("box_warp", scalar(1.0)),
        ("ray_start", scalar(2.25)),
        ("ray_end", scalar(3.3)),
        ("format_version", NpyArray { shape: vec![], data: NpyData::I64(vec![1]) }),
        ("source", NpyArray { shape: vec![], data: NpyData::Str("fuzz seed".into()) }),
    ]
}

fn npz_bytes(arrays: &[(&str, NpyArray)]) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    npz::write_npz(&mut out, arrays).unwrap();
    out.into_inner()
}

/// One zip entry with what the central directory claims about it.
struct Entry {
    name: String,
    data: Vec<u8>,
    declared_size: u64,
}

/// A stored zip written by hand, with zip64 extras where a declared size needs one.
fn build_zip(entries: &[Entry]) -> Vec<u8> {
    let (mut out, mut central) = (Vec::new(), Vec::new());
    for e in entries {
        let crc = crc32fast::hash(&e.data);
        let size = e.declared_size;
        let zip64 = size >= 0xFFFF_FFFF;
        let extra: Vec<u8> = if zip64 {
            [1u16.to_le_bytes().as_slice(), &16u16.to_le_bytes(), &size.to_le_bytes(), &size.to_le_bytes()]
                .concat()
        } else {
            vec![]
        };
        let s32 = if zip64 { 0xFFFF_FFFF } else { size as u32 };
        let name = e.name.as_bytes();
        let offset = out.len() as u32;
        let common = |v: &mut Vec<u8>| {
            v.extend(45u16.to_le_bytes()); // version needed
            v.extend(0u16.to_le_bytes()); // flags
            v.extend(0u16.to_le_bytes()); // stored
            v.extend(0u32.to_le_bytes()); // time, date
            v.extend(crc.to_le_bytes());
            v.extend(s32.to_le_bytes());
            v.extend(s32.to_le_bytes());
            v.extend((name.len() as u16).to_le_bytes());
            v.extend((extra.len() as u16).to_le_bytes());
        };
        out.extend(0x0403_4B50u32.to_le_bytes());
        common(&mut out);
        out.extend(name);
        out.extend(&extra);
        out.extend(&e.data);
        central.extend(0x0201_4B50u32.to_le_bytes());
        central.extend(45u16.to_le_bytes()); // made by
        common(&mut central);
        central.extend([0u8; 6]); // comment length, disk, internal attributes
        central.extend(0u32.to_le_bytes()); // external attributes
        central.extend(offset.to_le_bytes());
        central.extend(name);
        central.extend(&extra);
    }
    let n = entries.len() as u16;
    let cd_offset = out.len() as u32;
    let cd_len = central.len() as u32;
    out.extend(central);
    out.extend(0x0605_4B50u32.to_le_bytes());
    out.extend([0u8; 4]);
    out.extend(n.to_le_bytes());
    out.extend(n.to_le_bytes());
    out.extend(cd_len.to_le_bytes());
    out.extend(cd_offset.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out
}

fn entries_of(arrays: &[(&str, NpyArray)]) -> Vec<Entry> {
    arrays
        .iter()
        .map(|(k, a)| {
            let data = npz::write_npy(a);
            Entry { name: format!("{k}.npy"), declared_size: data.len() as u64, data }
        })
        .collect()
}

fn load_bytes(bytes: &[u8]) -> lp3d_renderer::Result<Triplane> {
    Triplane::from_reader(Cursor::new(bytes), bytes.len() as u64, Path::new("mem.npz"))
}

fn format_error(bytes: &[u8]) -> (String, String) {
    match load_bytes(bytes) {
        Err(Error::Format { field, message, .. }) => (field, message),
        other => panic!("expected a format error, got {other:?}"),
    }
}

#[test]
fn valid_file_loads() {
    let tri = load_bytes(&npz_bytes(&good_arrays())).unwrap();
    assert_eq!((tri.height, tri.width), (6, 7));
    assert_eq!(tri.source.as_deref(), Some("fuzz seed"));
    let hand = load_bytes(&build_zip(&entries_of(&good_arrays()))).unwrap();
    assert_eq!(hand, tri);
}

#[test]
fn zip64_size_claims_are_refused_before_allocating() {
    // Unchecked, a claim of 1 TiB aborts the process (Vec::with_capacity) and 2^64 - 16 panics.
    for claim in [1u64 << 40, u64::MAX - 15, 100 << 20] {
        let mut entries = entries_of(&good_arrays());
        entries[0].declared_size = claim;
        let (field, message) = format_error(&build_zip(&entries));
        assert_eq!(field, "planes");
        assert!(message.contains("cap") || message.contains("past the end"), "{message}");
    }
}

#[test]
fn npy_header_claims_are_refused_before_reading() {
    // A header claiming 1.5 TiB, and real planes over the 2048 cap.
    let npy = |h: &str, body: &[u8]| {
        let mut v = b"\x93NUMPY\x01\x00".to_vec();
        v.extend((h.len() as u16).to_le_bytes());
        v.extend(h.as_bytes());
        v.extend(body);
        v
    };
    let mut entries = entries_of(&good_arrays());
    entries[0].data =
        npy("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 32, 65536, 65536), }", &[0; 64]);
    entries[0].declared_size = entries[0].data.len() as u64;
    let (field, message) = format_error(&build_zip(&entries));
    assert_eq!(field, "planes");
    assert!(message.contains("truncated data"), "{message}");

    let mut arrays = good_arrays();
    arrays[0].1 = NpyArray { shape: vec![3, 32, 2050, 2], data: NpyData::F16(vec![0; 3 * 32 * 2050 * 2]) };
    let (field, message) = format_error(&npz_bytes(&arrays));
    assert_eq!(field, "planes");
    assert!(message.contains("[2, 2048]"), "{message}");
}

#[test]
fn one_spec_with_the_python_reader() {
    // Entries both readers refuse, naming the same field: a wrong shape or dtype, a value float32
    // cannot hold, an unknown format version.
    let with = |key: &str, a: NpyArray| {
        let mut arrays = good_arrays();
        arrays.iter_mut().find(|(k, _)| *k == key).unwrap().1 = a;
        npz_bytes(&arrays)
    };
    let (field, message) =
        format_error(&with("box_warp", NpyArray { shape: vec![1], data: NpyData::F64(vec![1.0]) }));
    assert_eq!((field.as_str(), message.contains("shape")), ("box_warp", true), "{message}");
    let (field, message) =
        format_error(&with("decoder_b0", NpyArray { shape: vec![64], data: NpyData::F16(vec![0; 64]) }));
    assert_eq!((field.as_str(), message.contains("dtype")), ("decoder_b0", true), "{message}");
    let (field, message) =
        format_error(&with("ray_end", NpyArray { shape: vec![], data: NpyData::F64(vec![1e300]) }));
    assert_eq!((field.as_str(), message.contains("float32")), ("ray_end", true), "{message}");
    let (field, _) =
        format_error(&with("ray_start", NpyArray { shape: vec![], data: NpyData::F64(vec![-1e-50]) }));
    assert_eq!(field, "ray_start");
    let (field, message) =
        format_error(&with("format_version", NpyArray { shape: vec![], data: NpyData::I64(vec![2]) }));
    assert_eq!(field, "format_version");
    assert!(message.contains("unknown format_version 2 ") && !message.contains("I64"), "{message}");
}

#[cfg(unix)]
#[test]
fn non_regular_files_are_refused_at_once() {
    use std::io::ErrorKind::{InvalidInput, IsADirectory};
    // Unchecked, a FIFO hangs the reader and a directory gives "Invalid argument (os error 22)".
    let dir = std::env::temp_dir().join(format!("lp3d-triplane-files-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let fifo = dir.join("pipe.npz");
    let _ = std::fs::remove_file(&fifo);
    // The mkfifo(1) program rather than libc::mkfifo: the workspace forbids unsafe code.
    let made = std::process::Command::new("mkfifo").args(["-m", "600"]).arg(&fifo).status().unwrap();
    assert!(made.success(), "mkfifo {}: {made}", fifo.display());
    for (path, words, expected) in [
        (fifo.as_path(), "FIFO", InvalidInput),
        (dir.as_path(), "is a directory", IsADirectory),
        (Path::new("/dev/zero"), "character device", InvalidInput),
        (Path::new("/dev/urandom"), "character device", InvalidInput),
    ] {
        match Triplane::load(path) {
            Err(e @ Error::Io { kind, .. }) => {
                let text = e.to_string();
                assert!(text.contains(words) && text.contains(path.to_str().unwrap()), "{text}");
                assert_eq!(kind, expected, "{text}");
            }
            other => panic!("{}: expected an I/O error, got {other:?}", path.display()),
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_missing_file_is_an_io_error_with_its_kind_and_source() {
    use std::error::Error as _;
    let path = std::env::temp_dir().join(format!("lp3d-no-such-file-{}.npz", std::process::id()));
    let e = Triplane::load(&path).unwrap_err();
    assert!(matches!(e, Error::Io { kind: std::io::ErrorKind::NotFound, .. }), "{e:?}");
    assert!(e.to_string().starts_with(&format!("{}: ", path.display())), "{e}");
    let source = e.source().and_then(|s| s.downcast_ref::<std::io::Error>()).expect("the io::Error");
    assert_eq!(source.kind(), std::io::ErrorKind::NotFound);
}

fn xorshift(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

/// Values that make size and offset fields interesting.
const INTERESTING: [u64; 10] =
    [0, 1, 0x7F, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, 1 << 40, u64::MAX - 15, u64::MAX];
/// Bytes a `.npy` header is made of.
const HEADER_BYTES: &[u8] = b"{}()':, 0123456789<>|fiuUOTrueFalsdescrfortran_ordershape\n";

/// One random mutation of `bytes`.
fn mutate(bytes: &mut Vec<u8>, state: &mut u64) {
    let at = |state: &mut u64, len: usize| (xorshift(state) as usize) % len.max(1);
    match xorshift(state) % 6 {
        0 => {
            let i = at(state, bytes.len());
            if let Some(b) = bytes.get_mut(i) {
                *b ^= 1 << (xorshift(state) % 8);
            }
        }
        1 => {
            let i = at(state, bytes.len());
            if let Some(b) = bytes.get_mut(i) {
                *b = xorshift(state) as u8;
            }
        }
        2 => {
            // An interesting 2-, 4- or 8-byte little-endian value over a field.
            let v = INTERESTING[at(state, INTERESTING.len())].to_le_bytes();
            let width = [2, 4, 8][at(state, 3)];
            let i = at(state, bytes.len());
            let end = (i + width).min(bytes.len());
            bytes[i..end].copy_from_slice(&v[..end - i]);
        }
        3 => {
            let n = at(state, bytes.len() + 1);
            bytes.truncate(n);
        }
        4 => {
            // A header character inside a `.npy` header.
            let starts: Vec<usize> =
                bytes.windows(6).enumerate().filter(|(_, w)| w == b"\x93NUMPY").map(|(i, _)| i).collect();
            if !starts.is_empty() {
                let s = starts[at(state, starts.len())];
                let i = (s + 10 + at(state, 80)).min(bytes.len().saturating_sub(1));
                if let Some(b) = bytes.get_mut(i) {
                    *b = HEADER_BYTES[at(state, HEADER_BYTES.len())];
                }
            }
        }
        _ => {
            let i = at(state, bytes.len());
            let n = at(state, 64).min(bytes.len() - i.min(bytes.len()));
            let chunk = bytes[i..i + n].to_vec();
            let j = at(state, bytes.len());
            bytes.splice(j..j, chunk);
        }
    }
}

/// Mutated files, seeded with valid ones and with the hostile cases above: every one must load or
/// give an error; a panic fails the test, an abort kills it. Bounded and deterministic. Half the
/// rounds mutate the archive's bytes; half mutate one entry's `.npy` and zip it again with a
/// correct CRC and size, so the mutation reaches the header and value checks.
#[test]
fn npz_fuzz() {
    const ROUNDS: usize = 5000;
    let mut seeds = vec![npz_bytes(&good_arrays()), build_zip(&entries_of(&good_arrays()))];
    for claim in [1u64 << 40, u64::MAX - 15] {
        let mut entries = entries_of(&good_arrays());
        entries[3].declared_size = claim;
        seeds.push(build_zip(&entries));
    }
    let (mut state, mut cases, mut accepted) = (0x9E37_79B9_7F4A_7C15u64, 0usize, 0usize);
    let mut check = |bytes: &[u8]| {
        match load_bytes(bytes) {
            Ok(_) => accepted += 1,
            Err(Error::Format { .. } | Error::Io { .. } | Error::InvalidInput { .. }) => {}
            Err(e) => panic!("unexpected error kind: {e:?}"),
        }
        cases += 1;
    };
    for seed in &seeds {
        for _ in 0..ROUNDS {
            let mut bytes = seed.clone();
            for _ in 0..1 + xorshift(&mut state) % 4 {
                mutate(&mut bytes, &mut state);
            }
            check(&bytes);
        }
    }
    for _ in 0..ROUNDS * 2 {
        let mut entries = entries_of(&good_arrays());
        let i = (xorshift(&mut state) as usize) % entries.len();
        for _ in 0..1 + xorshift(&mut state) % 3 {
            mutate(&mut entries[i].data, &mut state);
        }
        entries[i].declared_size = entries[i].data.len() as u64;
        check(&build_zip(&entries));
    }
    assert_eq!(cases, (seeds.len() + 2) * ROUNDS);
    // Some mutations (a flipped bit in a float) keep the file valid; most do not.
    assert!(accepted > 0 && accepted < cases, "{accepted} of {cases} accepted");
    println!("npz_fuzz: {cases} mutated files, {accepted} accepted");
}
