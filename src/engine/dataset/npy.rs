//! Minimal `.npy` reader: format versions 1.0, 2.0 and 3.0, little-endian
//! float64 (`'<f8'`), C order. Anything else is rejected with a message that
//! says what was found.

use std::path::Path;

use super::DatasetError;

/// A parsed float64 array (C order).
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl NpyArray {
    /// Element `(i, j)` of a 2-D array; `None` when out of range or not 2-D.
    pub fn get2(&self, i: usize, j: usize) -> Option<f64> {
        match self.shape[..] {
            [rows, cols] if i < rows && j < cols => self.data.get(i * cols + j).copied(),
            _ => None,
        }
    }

    /// Row `i` of a 2-D array; `None` when out of range or not 2-D.
    pub fn row(&self, i: usize) -> Option<&[f64]> {
        match self.shape[..] {
            [rows, cols] if i < rows => self.data.get(i * cols..(i + 1) * cols),
            _ => None,
        }
    }
}

const MAGIC: &[u8] = b"\x93NUMPY";

/// Parses the bytes of a `.npy` file. `path` is only used in error messages.
pub fn parse_npy(bytes: &[u8], path: &Path) -> Result<NpyArray, DatasetError> {
    let err = |message: String| DatasetError::Invalid { path: path.to_path_buf(), message };
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err(err("not a .npy file (bad magic string)".into()));
    }
    let (major, minor) = match (bytes.get(6), bytes.get(7)) {
        (Some(&a), Some(&b)) => (a, b),
        _ => return Err(err("truncated .npy header".into())),
    };
    let (header_len, header_start) = match major {
        1 => match bytes.get(8..10) {
            Some(b) => (u16::from_le_bytes([b[0], b[1]]) as usize, 10usize),
            None => return Err(err("truncated .npy header".into())),
        },
        2 | 3 => match bytes.get(8..12) {
            Some(b) => (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12),
            None => return Err(err("truncated .npy header".into())),
        },
        _ => {
            return Err(err(format!("unsupported .npy format version {major}.{minor}")));
        }
    };
    let header_end = header_start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| err("truncated .npy header".into()))?;
    let raw = &bytes[header_start..header_end];
    // Versions 1 and 2 use latin-1 headers, version 3 UTF-8; the keys and
    // values we accept are ASCII either way.
    let header: String = if major == 3 {
        std::str::from_utf8(raw).map_err(|_| err("npy header is not UTF-8".into()))?.to_owned()
    } else {
        raw.iter().map(|&b| b as char).collect()
    };
    let h = parse_header(&header).map_err(|m| err(format!("bad .npy header: {m}")))?;
    if h.descr != "<f8" {
        return Err(err(format!(
            "unsupported .npy dtype '{}' (only little-endian float64 '<f8' is supported)",
            h.descr
        )));
    }
    if h.fortran_order {
        return Err(err("Fortran-ordered .npy arrays are not supported (need C order)".into()));
    }
    let count = h
        .shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| err(format!("shape {:?} is too large", h.shape)))?;
    let body = &bytes[header_end..];
    let want = count.checked_mul(8).ok_or_else(|| err(format!("shape {:?} is too large", h.shape)))?;
    if body.len() != want {
        return Err(err(format!(
            "{} data bytes for shape {:?} ({} expected){}",
            body.len(),
            h.shape,
            want,
            if body.len() < want { ": file is truncated" } else { "" }
        )));
    }
    let data =
        body.chunks_exact(8).map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])).collect();
    Ok(NpyArray { shape: h.shape, data })
}

struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Parses the Python dict literal of an npy header, e.g.
/// `{'descr': '<f8', 'fortran_order': False, 'shape': (20, 17), }`.
fn parse_header(s: &str) -> Result<Header, String> {
    let mut p = Parser { s: s.as_bytes(), i: 0 };
    let (mut descr, mut fortran, mut shape) = (None, None, None);
    p.expect(b'{')?;
    loop {
        p.ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.string()?;
        p.ws();
        p.expect(b':')?;
        p.ws();
        match key.as_str() {
            "descr" => descr = Some(p.string()?),
            "fortran_order" => fortran = Some(p.boolean()?),
            "shape" => shape = Some(p.tuple()?),
            other => return Err(format!("unexpected key '{other}'")),
        }
        p.ws();
        if !p.eat(b',') {
            p.ws();
            p.expect(b'}')?;
            break;
        }
    }
    Ok(Header {
        descr: descr.ok_or("missing 'descr'")?,
        fortran_order: fortran.ok_or("missing 'fortran_order'")?,
        shape: shape.ok_or("missing 'shape'")?,
    })
}

struct Parser<'a> {
    s: &'a [u8],
    i: usize,
}

impl Parser<'_> {
    fn peek(&self) -> Option<u8> {
        self.s.get(self.i).copied()
    }
    fn ws(&mut self) {
        while matches!(self.peek(), Some(b' ' | b'\t' | b'\n' | b'\r')) {
            self.i += 1;
        }
    }
    fn eat(&mut self, c: u8) -> bool {
        if self.peek() == Some(c) {
            self.i += 1;
            true
        } else {
            false
        }
    }
    fn expect(&mut self, c: u8) -> Result<(), String> {
        self.ws();
        if self.eat(c) { Ok(()) } else { Err(format!("expected '{}' at byte {}", c as char, self.i)) }
    }
    fn string(&mut self) -> Result<String, String> {
        let q = match self.peek() {
            Some(q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("expected a string at byte {}", self.i)),
        };
        self.i += 1;
        let start = self.i;
        while let Some(c) = self.peek() {
            if c == q {
                let v = String::from_utf8_lossy(&self.s[start..self.i]).into_owned();
                self.i += 1;
                return Ok(v);
            }
            self.i += 1;
        }
        Err("unterminated string".into())
    }
    fn boolean(&mut self) -> Result<bool, String> {
        let rest = &self.s[self.i..];
        if rest.starts_with(b"True") {
            self.i += 4;
            Ok(true)
        } else if rest.starts_with(b"False") {
            self.i += 5;
            Ok(false)
        } else {
            Err(format!("expected True or False at byte {}", self.i))
        }
    }
    fn tuple(&mut self) -> Result<Vec<usize>, String> {
        self.expect(b'(')?;
        let mut v = Vec::new();
        loop {
            self.ws();
            if self.eat(b')') {
                return Ok(v);
            }
            let start = self.i;
            while matches!(self.peek(), Some(b'0'..=b'9')) {
                self.i += 1;
            }
            let digits = std::str::from_utf8(&self.s[start..self.i]).unwrap_or("");
            let n = digits.parse::<usize>().map_err(|_| format!("expected a dimension at byte {start}"))?;
            v.push(n);
            self.ws();
            if !self.eat(b',') {
                self.expect(b')')?;
                return Ok(v);
            }
        }
    }
}

/// Serialises a float64 array as `.npy` (version `major`.0).
pub fn npy_bytes(shape: &[usize], data: &[f64], major: u8) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_s = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape_s}, }}");
    let prefix = if major == 1 { 10 } else { 12 };
    while (prefix + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    out.push(major);
    out.push(0);
    if major == 1 {
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("x.npy")
    }

    #[test]
    fn npy_parses_all_versions() {
        let data: Vec<f64> = (0..6).map(|i| i as f64 * 0.5).collect();
        for major in [1, 2, 3] {
            let a = parse_npy(&npy_bytes(&[2, 3], &data, major), p()).unwrap();
            assert_eq!(a.shape, vec![2, 3]);
            assert_eq!(a.data, data);
            assert_eq!(a.get2(1, 2), Some(2.5));
            assert_eq!(a.get2(2, 0), None);
            assert_eq!(a.row(1), Some(&data[3..6]));
        }
        let a = parse_npy(&npy_bytes(&[4], &data[..4], 1), p()).unwrap();
        assert_eq!(a.shape, vec![4]);
    }

    fn invalid_msg(r: Result<NpyArray, DatasetError>) -> String {
        match r {
            Err(DatasetError::Invalid { message, .. }) => message,
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn npy_rejects_bad_input() {
        let good = npy_bytes(&[2, 3], &[1.0; 6], 1);
        // Every truncation is an error, never a panic.
        for n in 0..good.len() {
            assert!(parse_npy(&good[..n], p()).is_err(), "truncated at {n}");
        }
        assert!(invalid_msg(parse_npy(&good[..good.len() - 3], p())).contains("truncated"));
        // Garbage.
        assert!(invalid_msg(parse_npy(b"hello world, not numpy", p())).contains("magic"));
        let mut extra = good.clone();
        extra.push(0);
        assert!(parse_npy(&extra, p()).is_err());
        // Unsupported version, dtype, order.
        let mut v9 = good.clone();
        v9[6] = 9;
        assert!(invalid_msg(parse_npy(&v9, p())).contains("version 9.0"));
        // Same-length edits of the header keep the layout valid.
        let edit = |from: &str, to: &str| {
            let (from, to) = (from.as_bytes(), to.as_bytes());
            let mut b = good.clone();
            let at = b.windows(from.len()).position(|w| w == from).unwrap();
            b[at..at + to.len()].copy_from_slice(to);
            b
        };
        assert!(invalid_msg(parse_npy(&edit("<f8", "<f4"), p())).contains("'<f4'"));
        assert!(invalid_msg(parse_npy(&edit("<f8", ">f8"), p())).contains("'>f8'"));
        assert!(invalid_msg(parse_npy(&edit("False", "True "), p())).contains("Fortran"));
        assert!(invalid_msg(parse_npy(&edit("(2, 3)", "(2, x)"), p())).contains("header"));
        assert!(invalid_msg(parse_npy(&edit("'shape'", "'shaep'"), p())).contains("header"));
        // Huge shapes do not overflow or allocate.
        let huge = npy_bytes(&[usize::MAX / 2, 3], &[], 1);
        assert!(invalid_msg(parse_npy(&huge, p())).contains("too large"));
        let big = npy_bytes(&[usize::MAX / 64, 3], &[], 2);
        assert!(invalid_msg(parse_npy(&big, p())).contains("truncated"));
        // Random bytes after a valid magic.
        let mut junk = b"\x93NUMPY\x01\x00\xff\xff".to_vec();
        junk.extend((0..300u32).map(|i| (i * 37 % 251) as u8));
        assert!(parse_npy(&junk, p()).is_err());
    }
}
