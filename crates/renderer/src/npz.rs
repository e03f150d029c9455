//! A small, strict reader and writer for NumPy `.npy` arrays inside `.npz` (zip) files:
//! little-endian numeric dtypes and unicode scalars only. Object arrays are refused
//! outright; nothing here can execute code.

use std::io::{Read, Seek, Write};

/// Element data of one array.
#[derive(Debug, Clone, PartialEq)]
pub enum NpyData {
    F16(Vec<u16>),
    F32(Vec<f32>),
    F64(Vec<f64>),
    I64(Vec<i64>),
    I32(Vec<i32>),
    /// A unicode string (`<U…`), 0-d.
    Str(String),
}

#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: NpyData,
}

impl NpyArray {
    pub fn f32(shape: Vec<usize>, data: Vec<f32>) -> Self {
        NpyArray { shape, data: NpyData::F32(data) }
    }

    pub fn dtype_name(&self) -> &'static str {
        match self.data {
            NpyData::F16(_) => "float16",
            NpyData::F32(_) => "float32",
            NpyData::F64(_) => "float64",
            NpyData::I64(_) => "int64",
            NpyData::I32(_) => "int32",
            NpyData::Str(_) => "str",
        }
    }

    /// Values as f32 (floats converted; integers and strings refused).
    pub fn to_f32(&self) -> Option<Vec<f32>> {
        match &self.data {
            NpyData::F16(v) => Some(v.iter().map(|&b| half::f16::from_bits(b).to_f32()).collect()),
            NpyData::F32(v) => Some(v.clone()),
            NpyData::F64(v) => Some(v.iter().map(|&x| x as f32).collect()),
            _ => None,
        }
    }

    /// A scalar (0-d or one element) as f64.
    pub fn scalar_f64(&self) -> Option<f64> {
        if self.shape.iter().product::<usize>() != 1 {
            return None;
        }
        match &self.data {
            NpyData::F16(v) => Some(half::f16::from_bits(v[0]).to_f64()),
            NpyData::F32(v) => Some(v[0] as f64),
            NpyData::F64(v) => Some(v[0]),
            NpyData::I64(v) => Some(v[0] as f64),
            NpyData::I32(v) => Some(v[0] as f64),
            NpyData::Str(_) => None,
        }
    }
}

/// Parses one `.npy` byte stream. Errors are plain messages; the caller adds file and key.
pub fn parse_npy(bytes: &[u8]) -> Result<NpyArray, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy array (bad magic)".into());
    }
    let major = bytes[6];
    let (header_len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err("truncated header".into());
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(format!("unsupported .npy version {v}")),
    };
    let header = bytes.get(start..start + header_len).ok_or("truncated header")?;
    let header = std::str::from_utf8(header).map_err(|_| "header is not text")?;
    let descr = dict_value(header, "descr").ok_or("header has no 'descr'")?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    let fortran = dict_value(header, "fortran_order").ok_or("header has no 'fortran_order'")?;
    if fortran.trim() != "False" {
        return Err("Fortran-ordered arrays are not supported".into());
    }
    let shape_text = dict_value(header, "shape").ok_or("header has no 'shape'")?;
    let shape: Vec<usize> = shape_text
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("bad shape {shape_text}")))
        .collect::<Result<_, _>>()?;
    let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or("shape too large")?;
    let body = &bytes[start + header_len..];
    if descr.contains('O') {
        return Err("object arrays are not allowed (they would need pickle)".into());
    }
    let take = |width: usize| -> Result<&[u8], String> {
        let n = count.checked_mul(width).ok_or("shape too large")?;
        body.get(..n).ok_or_else(|| format!("truncated data: expected {n} bytes, found {}", body.len()))
    };
    let data = match descr {
        "<f2" => NpyData::F16(take(2)?.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect()),
        "<f4" => NpyData::F32(
            take(4)?.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect(),
        ),
        "<f8" => NpyData::F64(
            take(8)?.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect(),
        ),
        "<i8" => NpyData::I64(
            take(8)?.chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().unwrap())).collect(),
        ),
        "<i4" => NpyData::I32(
            take(4)?.chunks_exact(4).map(|c| i32::from_le_bytes(c.try_into().unwrap())).collect(),
        ),
        d if d.starts_with("<U") && count == 1 => {
            let n: usize = d[2..].parse().map_err(|_| format!("bad dtype {d}"))?;
            let raw = take(4 * n)?;
            let s: String = raw
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
                .take_while(|&u| u != 0)
                .map(|u| char::from_u32(u).ok_or("invalid unicode"))
                .collect::<Result<_, _>>()?;
            NpyData::Str(s)
        }
        d => return Err(format!("unsupported dtype '{d}'")),
    };
    Ok(NpyArray { shape, data })
}

/// Finds `'key': value` in a .npy header dict and returns the value text.
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let pat = format!("'{key}':");
    let at = header.find(&pat)? + pat.len();
    let rest = header[at..].trim_start();
    let end = if rest.starts_with('(') { rest.find(')')? + 1 } else { rest.find([',', '}'])? };
    Some(&rest[..end])
}

/// Serialises one array as `.npy` version 1.0.
pub fn write_npy(array: &NpyArray) -> Vec<u8> {
    let (descr, body): (String, Vec<u8>) = match &array.data {
        NpyData::F16(v) => ("<f2".into(), v.iter().flat_map(|x| x.to_le_bytes()).collect()),
        NpyData::F32(v) => ("<f4".into(), v.iter().flat_map(|x| x.to_le_bytes()).collect()),
        NpyData::F64(v) => ("<f8".into(), v.iter().flat_map(|x| x.to_le_bytes()).collect()),
        NpyData::I64(v) => ("<i8".into(), v.iter().flat_map(|x| x.to_le_bytes()).collect()),
        NpyData::I32(v) => ("<i4".into(), v.iter().flat_map(|x| x.to_le_bytes()).collect()),
        NpyData::Str(s) => {
            let n = s.chars().count().max(1);
            let mut b: Vec<u8> = s.chars().flat_map(|c| (c as u32).to_le_bytes()).collect();
            b.resize(4 * n, 0);
            (format!("<U{n}"), b)
        }
    };
    let shape = match array.shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", array.shape[0]),
        _ => format!("({})", array.shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    // Pad so that magic + version + length + header is a multiple of 64, ending in '\n'.
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + body.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&body);
    out
}

/// Reads every array of an `.npz` archive, in archive order, as (key, array).
pub fn read_npz<R: Read + Seek>(reader: R) -> Result<Vec<(String, NpyArray)>, (String, String)> {
    let mut zip = zip::ZipArchive::new(reader)
        .map_err(|e| ("<archive>".to_string(), format!("not a valid .npz (zip) file: {e}")))?;
    let mut out = Vec::with_capacity(zip.len());
    for i in 0..zip.len() {
        let mut entry =
            zip.by_index(i).map_err(|e| ("<archive>".to_string(), format!("corrupt entry {i}: {e}")))?;
        let name =
            entry.name().map_err(|e| ("<archive>".to_string(), format!("bad entry name: {e}")))?.to_string();
        let key = name.strip_suffix(".npy").unwrap_or(&name).to_string();
        let mut bytes = Vec::with_capacity(entry.size() as usize);
        entry.read_to_end(&mut bytes).map_err(|e| (key.clone(), format!("cannot read: {e}")))?;
        let array = parse_npy(&bytes).map_err(|m| (key.clone(), m))?;
        out.push((key, array));
    }
    Ok(out)
}

/// Writes arrays as an uncompressed `.npz` (what `numpy.savez` writes).
pub fn write_npz<W: Write + Seek>(writer: W, arrays: &[(&str, NpyArray)]) -> std::io::Result<()> {
    let mut zip = zip::ZipWriter::new(writer);
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(true);
    for (key, array) in arrays {
        zip.start_file(format!("{key}.npy"), options).map_err(std::io::Error::other)?;
        zip.write_all(&write_npy(array))?;
    }
    zip.finish().map_err(std::io::Error::other)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_round_trip_all_dtypes() {
        let cases = vec![
            NpyArray { shape: vec![2, 3], data: NpyData::F32(vec![1.0, -2.0, 3.5, 0.0, 1e-8, 7.0]) },
            NpyArray { shape: vec![3], data: NpyData::F16(vec![0x3c00, 0xc000, 0x0001]) },
            NpyArray { shape: vec![], data: NpyData::F64(vec![2.25]) },
            NpyArray { shape: vec![], data: NpyData::I64(vec![1]) },
            NpyArray { shape: vec![], data: NpyData::Str("procedural seed 3 — ü".into()) },
        ];
        for a in cases {
            let bytes = write_npy(&a);
            assert_eq!(parse_npy(&bytes).unwrap(), a);
        }
    }

    #[test]
    fn refuses_objects_and_truncation() {
        let mut bytes = write_npy(&NpyArray::f32(vec![4], vec![1.0; 4]));
        let good_len = bytes.len();
        bytes.truncate(good_len - 3);
        assert!(parse_npy(&bytes).unwrap_err().contains("truncated"));
        let h = "{'descr': '|O', 'fortran_order': False, 'shape': (1,), }\n";
        let mut obj = b"\x93NUMPY\x01\x00".to_vec();
        obj.extend((h.len() as u16).to_le_bytes());
        obj.extend(h.as_bytes());
        obj.extend([0u8; 8]);
        assert!(parse_npy(&obj).unwrap_err().contains("object"));
    }
}
