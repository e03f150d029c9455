//! One `.npy` array: its dtypes, its header (parsed by a strict grammar, every claim checked
//! against the entry's size before data is read), its data, and writing it.

use std::io::Read;

/// Largest `.npy` header text (numpy's own default cap; numpy writes about 128 bytes).
pub const MAX_NPY_HEADER_BYTES: usize = 10_000;

const NPY_MAGIC: &[u8; 6] = b"\x93NUMPY";

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

/// The element types the reader accepts (exactly these `descr` strings).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    F16,
    F32,
    F64,
    I32,
    I64,
    /// `<U{n}`: n UTF-32LE code units (a 0-d string).
    Unicode(usize),
}

impl Dtype {
    /// Parses a `descr`; anything but little-endian `f2 f4 f8 i4 i8` and `<U{n}` is refused.
    pub fn parse(descr: &str) -> Result<Dtype, String> {
        Ok(match descr {
            "<f2" => Dtype::F16,
            "<f4" => Dtype::F32,
            "<f8" => Dtype::F64,
            "<i4" => Dtype::I32,
            "<i8" => Dtype::I64,
            d if d.contains('O') => {
                return Err("object arrays are not allowed (they would need pickle)".into())
            }
            d => match d.strip_prefix("<U") {
                Some(n) if !n.is_empty() && n.len() <= 10 && n.bytes().all(|b| b.is_ascii_digit()) => {
                    Dtype::Unicode(n.parse().map_err(|_| format!("unsupported dtype '{d}'"))?)
                }
                _ => return Err(format!("unsupported dtype '{d}'")),
            },
        })
    }

    /// The `descr` string, as numpy writes it.
    pub fn descr(&self) -> String {
        match self {
            Dtype::F16 => "<f2".into(),
            Dtype::F32 => "<f4".into(),
            Dtype::F64 => "<f8".into(),
            Dtype::I32 => "<i4".into(),
            Dtype::I64 => "<i8".into(),
            Dtype::Unicode(n) => format!("<U{n}"),
        }
    }

    /// The numpy name, for messages: `float32`, or `<U5 (a string)`.
    pub fn name(&self) -> String {
        match self {
            Dtype::F16 => "float16".into(),
            Dtype::F32 => "float32".into(),
            Dtype::F64 => "float64".into(),
            Dtype::I32 => "int32".into(),
            Dtype::I64 => "int64".into(),
            Dtype::Unicode(n) => format!("<U{n} (a string)"),
        }
    }

    /// Bytes per element (None when a `<U{n}` is too long to size).
    pub fn item_bytes(&self) -> Option<usize> {
        match self {
            Dtype::F16 => Some(2),
            Dtype::F32 | Dtype::I32 => Some(4),
            Dtype::F64 | Dtype::I64 => Some(8),
            Dtype::Unicode(n) => n.checked_mul(4),
        }
    }
}

/// What a `.npy` header declares, checked against the size of the bytes that follow it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyHeader {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// Bytes before the data: magic, version, header length and header text.
    pub data_offset: usize,
    /// Bytes of data the shape and dtype imply (equal to what follows the header).
    pub data_bytes: usize,
}

impl NpyHeader {
    pub fn count(&self) -> usize {
        self.shape.iter().product()
    }

    /// The shape as Python writes a tuple: `()`, `(25,)`, `(3, 32, 8, 8)`.
    pub fn shape_text(&self) -> String {
        shape_text(&self.shape)
    }
}

/// A shape as Python writes a tuple.
pub fn shape_text(shape: &[usize]) -> String {
    match shape {
        [] => "()".into(),
        [n] => format!("({n},)"),
        s => format!("({})", s.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    }
}

pub(super) fn io_message(e: std::io::Error) -> String {
    if e.kind() == std::io::ErrorKind::UnexpectedEof {
        "truncated data".into()
    } else {
        format!("corrupt data ({e})")
    }
}

/// Reads and checks a `.npy` header from `r`, an entry of `entry_bytes` bytes in all. On success
/// `r` is positioned at the data, and the data is exactly `data_bytes` long.
pub fn read_npy_header<R: Read>(r: &mut R, entry_bytes: u64) -> Result<NpyHeader, String> {
    if entry_bytes < 10 {
        return Err(format!("not a .npy array (only {entry_bytes} bytes)"));
    }
    let mut pre = [0u8; 8];
    r.read_exact(&mut pre).map_err(io_message)?;
    if &pre[..6] != NPY_MAGIC {
        return Err("not a .npy array (bad magic)".into());
    }
    let (len, prefix) = match (pre[6], pre[7]) {
        (1, 0) => {
            let mut b = [0u8; 2];
            r.read_exact(&mut b).map_err(io_message)?;
            (u16::from_le_bytes(b) as u64, 10u64)
        }
        (2 | 3, 0) => {
            let mut b = [0u8; 4];
            r.read_exact(&mut b).map_err(io_message)?;
            (u32::from_le_bytes(b) as u64, 12u64)
        }
        (major, minor) => return Err(format!("unsupported .npy version {major}.{minor}")),
    };
    if len > MAX_NPY_HEADER_BYTES as u64 {
        return Err(format!("header of {len} bytes is larger than the cap of {MAX_NPY_HEADER_BYTES}"));
    }
    if prefix + len > entry_bytes {
        return Err(format!("truncated header: {len} bytes declared, the entry holds {entry_bytes} in all"));
    }
    let mut text = vec![0u8; len as usize];
    r.read_exact(&mut text).map_err(io_message)?;
    let text = std::str::from_utf8(&text).ok().filter(|t| t.is_ascii()).ok_or("header is not ASCII text")?;
    let (descr, fortran, shape) = parse_header_dict(text)?;
    let dtype = Dtype::parse(descr)?;
    if fortran {
        return Err("Fortran-ordered arrays are not supported (write C order)".into());
    }
    if matches!(dtype, Dtype::Unicode(_)) && !shape.is_empty() {
        return Err(format!("a unicode array must be 0-d (one string), got shape {}", shape_text(&shape)));
    }
    let too_large = || format!("shape {} of {descr} is too large", shape_text(&shape));
    let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or_else(too_large)?;
    let data_bytes = dtype.item_bytes().and_then(|b| b.checked_mul(count)).ok_or_else(too_large)?;
    let data_offset = prefix + len;
    let have = entry_bytes - data_offset;
    if data_bytes as u64 > have {
        return Err(format!(
            "truncated data: shape {} of {descr} needs {data_bytes} bytes, the entry holds {have}",
            shape_text(&shape)
        ));
    }
    if (data_bytes as u64) < have {
        return Err(format!(
            "{} unexpected bytes after the data (shape {} of {descr} needs {data_bytes})",
            have - data_bytes as u64,
            shape_text(&shape)
        ));
    }
    Ok(NpyHeader { dtype, shape, data_offset: data_offset as usize, data_bytes })
}

/// Reads `count` little-endian elements straight into their typed buffer (no byte copy).
fn read_pod<T: bytemuck::Pod, R: Read>(
    r: &mut R,
    count: usize,
    from_le: fn(T) -> T,
) -> Result<Vec<T>, String> {
    let mut v = vec![T::zeroed(); count];
    r.read_exact(bytemuck::cast_slice_mut(&mut v)).map_err(io_message)?;
    if cfg!(target_endian = "big") {
        v.iter_mut().for_each(|x| *x = from_le(*x));
    }
    Ok(v)
}

/// Reads the data [`read_npy_header`] described, then checks the reader is at its end (for a zip
/// entry, that final read is what verifies its CRC-32).
pub fn read_npy_data<R: Read>(r: &mut R, header: &NpyHeader) -> Result<NpyData, String> {
    let n = header.count();
    let data = match header.dtype {
        Dtype::F16 => NpyData::F16(read_pod(r, n, u16::from_le)?),
        Dtype::F32 => NpyData::F32(read_pod(r, n, |x: f32| f32::from_bits(u32::from_le(x.to_bits())))?),
        Dtype::F64 => NpyData::F64(read_pod(r, n, |x: f64| f64::from_bits(u64::from_le(x.to_bits())))?),
        Dtype::I32 => NpyData::I32(read_pod(r, n, i32::from_le)?),
        Dtype::I64 => NpyData::I64(read_pod(r, n, i64::from_le)?),
        Dtype::Unicode(chars) => {
            let units: Vec<u32> = read_pod(r, chars, u32::from_le)?;
            let s: String = units
                .iter()
                .map(|&u| char::from_u32(u).ok_or_else(|| format!("invalid unicode code point {u:#x}")))
                .collect::<Result<_, _>>()?;
            // numpy pads with NULs and strips them on read; an inner NUL is kept, as numpy does.
            NpyData::Str(s.trim_end_matches('\0').to_string())
        }
    };
    let mut probe = [0u8; 1];
    match r.read(&mut probe) {
        Ok(0) => Ok(data),
        Ok(_) => Err("data continues past its declared size".into()),
        Err(e) => Err(io_message(e)),
    }
}

/// Parses one whole `.npy` byte stream. Errors are plain messages; the caller adds file and key.
pub fn parse_npy(bytes: &[u8]) -> Result<NpyArray, String> {
    let mut cursor = std::io::Cursor::new(bytes);
    let header = read_npy_header(&mut cursor, bytes.len() as u64)?;
    let data = read_npy_data(&mut cursor, &header)?;
    Ok(NpyArray { shape: header.shape, data })
}

/// A value in a `.npy` header dict.
enum HeaderValue<'a> {
    Str(&'a str),
    Bool(bool),
    Tuple(Vec<usize>),
}

/// The header dict's grammar, the subset of Python literals numpy writes:
/// `{'descr': '<f4', 'fortran_order': False, 'shape': (3, 32, 8, 8), }` plus padding. Strings
/// without escapes, `True`/`False`, tuples of decimal integers (one element needs its comma).
/// `lp3d.render.npz_reader` parses the same grammar, so both readers agree on every header.
struct HeaderParser<'a> {
    s: &'a str,
    i: usize,
}

impl<'a> HeaderParser<'a> {
    fn peek(&self) -> Option<u8> {
        self.s.as_bytes().get(self.i).copied()
    }

    fn ws(&mut self) {
        while matches!(self.peek(), Some(b' ' | b'\t' | b'\n' | b'\r')) {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        self.ws();
        let hit = self.peek() == Some(c);
        if hit {
            self.i += 1;
        }
        hit
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("bad .npy header: expected '{}' at offset {}", c as char, self.i))
        }
    }

    fn string(&mut self) -> Result<&'a str, String> {
        self.ws();
        let q = self.peek().filter(|&q| q == b'\'' || q == b'"');
        let q = q.ok_or_else(|| format!("bad .npy header: expected a string at offset {}", self.i))?;
        let start = self.i + 1;
        let len = self.s[start..].find(q as char).ok_or("bad .npy header: unterminated string")?;
        let text = &self.s[start..start + len];
        if text.contains('\\') {
            return Err("bad .npy header: escapes in strings are not supported".into());
        }
        self.i = start + len + 1;
        Ok(text)
    }

    fn int(&mut self) -> Result<usize, String> {
        self.ws();
        let start = self.i;
        while matches!(self.peek(), Some(b'0'..=b'9')) {
            self.i += 1;
        }
        let digits = &self.s[start..self.i];
        if digits.is_empty() {
            return Err(format!("bad .npy header: expected a non-negative integer at offset {start}"));
        }
        digits.parse::<usize>().map_err(|_| format!("bad .npy header: dimension {digits} is too large"))
    }

    fn value(&mut self) -> Result<HeaderValue<'a>, String> {
        self.ws();
        let rest = &self.s[self.i..];
        if rest.starts_with("True") || rest.starts_with("False") {
            let t = rest.starts_with("True");
            self.i += if t { 4 } else { 5 };
            return Ok(HeaderValue::Bool(t));
        }
        if self.eat(b'(') {
            let mut dims = Vec::new();
            if self.eat(b')') {
                return Ok(HeaderValue::Tuple(dims));
            }
            loop {
                dims.push(self.int()?);
                if self.eat(b')') {
                    if dims.len() == 1 {
                        return Err(
                            "bad .npy header: a 1-d shape needs its trailing comma, as in (5,)".into()
                        );
                    }
                    return Ok(HeaderValue::Tuple(dims));
                }
                self.expect(b',')?;
                if self.eat(b')') {
                    return Ok(HeaderValue::Tuple(dims));
                }
            }
        }
        Ok(HeaderValue::Str(self.string()?))
    }
}

/// (descr, fortran_order, shape) of a header dict; exactly those three keys, once each.
fn parse_header_dict(text: &str) -> Result<(&str, bool, Vec<usize>), String> {
    let mut p = HeaderParser { s: text, i: 0 };
    let (mut descr, mut fortran, mut shape) = (None, None, None);
    p.expect(b'{')?;
    while !p.eat(b'}') {
        let key = p.string()?;
        p.expect(b':')?;
        let value = p.value()?;
        let slot_taken = match (key, value) {
            ("descr", HeaderValue::Str(s)) => descr.replace(s).is_some(),
            ("fortran_order", HeaderValue::Bool(b)) => fortran.replace(b).is_some(),
            ("shape", HeaderValue::Tuple(t)) => shape.replace(t).is_some(),
            ("descr", _) => return Err("bad .npy header: 'descr' must be a string".into()),
            ("fortran_order", _) => {
                return Err("bad .npy header: 'fortran_order' must be True or False".into())
            }
            ("shape", _) => return Err("bad .npy header: 'shape' must be a tuple of integers".into()),
            (k, _) => return Err(format!("bad .npy header: unexpected key '{k}'")),
        };
        if slot_taken {
            return Err(format!("bad .npy header: key '{key}' appears twice"));
        }
        if !p.eat(b',') {
            p.expect(b'}')?;
            break;
        }
    }
    p.ws();
    if p.i != text.len() {
        return Err(format!("bad .npy header: unexpected text after the dict at offset {}", p.i));
    }
    match (descr, fortran, shape) {
        (Some(d), Some(f), Some(s)) => Ok((d, f, s)),
        (None, ..) => Err("bad .npy header: no 'descr'".into()),
        (_, None, _) => Err("bad .npy header: no 'fortran_order'".into()),
        (.., None) => Err("bad .npy header: no 'shape'".into()),
    }
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

    fn npy_with_header(header: &str, body: &[u8]) -> Vec<u8> {
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend((header.len() as u16).to_le_bytes());
        out.extend(header.as_bytes());
        out.extend(body);
        out
    }

    #[test]
    fn refuses_objects_and_truncation() {
        let mut bytes = write_npy(&NpyArray::f32(vec![4], vec![1.0; 4]));
        let good_len = bytes.len();
        bytes.truncate(good_len - 3);
        assert!(parse_npy(&bytes).unwrap_err().contains("truncated"));
        let obj = npy_with_header("{'descr': '|O', 'fortran_order': False, 'shape': (1,), }\n", &[0; 8]);
        assert!(parse_npy(&obj).unwrap_err().contains("object"));
    }

    #[test]
    fn header_claims_are_checked_before_reading() {
        // 1.5 TiB claimed by a header over 8 bytes of data: an error, not an allocation.
        let huge = npy_with_header(
            "{'descr': '<f4', 'fortran_order': False, 'shape': (3, 32, 65536, 65536), }\n",
            &[0; 8],
        );
        assert!(parse_npy(&huge).unwrap_err().contains("truncated data"), "{:?}", parse_npy(&huge));
        let overflow = npy_with_header(
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4294967296, 4294967296), }",
            &[],
        );
        assert!(parse_npy(&overflow).unwrap_err().contains("too large"));
        let absurd =
            npy_with_header("{'descr': '<U4611686018427387904', 'fortran_order': False, 'shape': (), }", &[]);
        assert!(parse_npy(&absurd).unwrap_err().contains("unsupported dtype"));
        let long = npy_with_header("{'descr': '<U4611686018', 'fortran_order': False, 'shape': (), }", &[]);
        assert!(parse_npy(&long).unwrap_err().contains("truncated data"));
        let fortran = npy_with_header("{'descr': '<f4', 'fortran_order': True, 'shape': (2, 2), }", &[0; 16]);
        assert!(parse_npy(&fortran).unwrap_err().contains("Fortran"));
        let trailing = npy_with_header("{'descr': '<f4', 'fortran_order': False, 'shape': (1,), }", &[0; 8]);
        assert!(parse_npy(&trailing).unwrap_err().contains("unexpected bytes"));
        let mut big_header = b"\x93NUMPY\x02\x00".to_vec();
        big_header.extend(u32::MAX.to_le_bytes());
        assert!(parse_npy(&big_header).unwrap_err().contains("cap"));
    }

    #[test]
    fn header_grammar() {
        let ok = |h: &str| parse_header_dict(h).map(|(d, f, s)| (d.to_string(), f, s));
        assert_eq!(
            ok("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 2), }   \n").unwrap(),
            ("<f4".into(), false, vec![3, 2])
        );
        assert_eq!(
            ok("{\"shape\":(5,),\"descr\":\"<i8\",\"fortran_order\":False}").unwrap(),
            ("<i8".into(), false, vec![5])
        );
        assert_eq!(
            ok("{'descr': '<f8', 'fortran_order': False, 'shape': ()}").unwrap().2,
            Vec::<usize>::new()
        );
        for bad in [
            "{'descr': '<f4', 'fortran_order': False, 'shape': (5), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (-1,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999999999999999,), }",
            "{'descr': '<f4', 'descr': '<f8', 'fortran_order': False, 'shape': (1,), }",
            "{'descr': '<f4', 'fortran_order': False, }",
            "{'descr': '<f4', 'fortran_order': 0, 'shape': (1,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), 'x': 1}",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), } x",
            "{'descr': '<f\\4', 'fortran_order': False, 'shape': (1,), }",
            "{'descr': '<f4', 'fortran_order': False, 'shape': (1,)",
            "",
        ] {
            assert!(ok(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn unicode_strips_trailing_nuls_only() {
        let body: Vec<u8> =
            ['a', '\0', 'b', '\0', '\0'].iter().flat_map(|&c| (c as u32).to_le_bytes()).collect();
        let a = parse_npy(&npy_with_header("{'descr': '<U5', 'fortran_order': False, 'shape': (), }", &body))
            .unwrap();
        assert_eq!(a.data, NpyData::Str("a\0b".into()));
        let bad = parse_npy(&npy_with_header(
            "{'descr': '<U1', 'fortran_order': False, 'shape': (), }",
            &0xD800u32.to_le_bytes(),
        ));
        assert!(bad.unwrap_err().contains("unicode"));
    }
}
