//! USD's binary layer format (the "crate" file, `.usdc`) at version 0.8.0,
//! written from a list of specs: what a USDZ carries to AR Quick Look, a
//! third the size of the same stage as text (USDA spells out every number).
//! 0.8.0 is what USD itself (26.11) writes for a stage like ours: no
//! reader needs more than USD's own files ask. Only the parts our stages
//! use are here: prims,
//! attributes with a default or a connection, relationships, and the value
//! types they hold (docs/design/mesh.md says why no crate on crates.io
//! serves).
//!
//! The layout: an 88-byte header, the values that do not fit in a field's
//! 64-bit descriptor, then six sections (tokens, strings, fields, field
//! sets, paths, specs) and their table of contents. Integer arrays of 16 or
//! more, and every integer list of the sections, are delta-coded (USD's
//! `Usd_IntegerCompression`) then LZ4-compressed in USD's framing.

use std::collections::HashMap;

/// A field's value.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    Token(String),
    Bool(bool),
    Float(f32),
    Double(f64),
    String(String),
    Asset(String),
    Vec3f([f32; 3]),
    Ints(Vec<i32>),
    Vec2fs(Vec<[f32; 2]>),
    Vec3fs(Vec<[f32; 3]>),
    /// A list of tokens (a prim's children, its properties).
    Tokens(Vec<String>),
    /// Tokens prepended to what weaker layers say (`prepend apiSchemas`).
    PrependTokens(Vec<String>),
    /// Paths, explicitly (a relationship's targets, a connection's sources).
    Paths(Vec<String>),
    /// A prim's specifier: always `def` here.
    Def,
    /// An attribute's variability: uniform or varying.
    Uniform(bool),
}

/// What a spec describes (USD's `SdfSpecType`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SpecKind {
    Attribute = 1,
    Prim = 6,
    PseudoRoot = 7,
    Relationship = 8,
}

/// One spec: its path (`/A/B` a prim, `/A/B.name` a property), what it is,
/// and its fields.
#[derive(Clone, Debug)]
pub struct Spec {
    pub path: String,
    pub kind: SpecKind,
    pub fields: Vec<(&'static str, Value)>,
}

/// USD's type numbers (`crateDataTypes.h`).
mod ty {
    pub const BOOL: u64 = 1;
    pub const INT: u64 = 3;
    pub const FLOAT: u64 = 8;
    pub const DOUBLE: u64 = 9;
    pub const STRING: u64 = 10;
    pub const TOKEN: u64 = 11;
    pub const ASSET: u64 = 12;
    pub const VEC2F: u64 = 20;
    pub const VEC3F: u64 = 24;
    pub const TOKEN_LIST_OP: u64 = 32;
    pub const PATH_LIST_OP: u64 = 34;
    pub const TOKEN_VECTOR: u64 = 41;
    pub const SPECIFIER: u64 = 42;
    pub const VARIABILITY: u64 = 44;
}

const ARRAY: u64 = 1 << 63;
const INLINED: u64 = 1 << 62;
const COMPRESSED: u64 = 1 << 61;
/// Integer arrays shorter than this are stored raw (USD reads them so).
const MIN_COMPRESSED: usize = 16;
/// The end of a field set.
const END: u32 = u32::MAX;

/// The layer `specs` describe, as a crate file. Every path a spec or a
/// value names must be absolute; a property's prim needs its own spec.
pub fn write(specs: &[Spec]) -> Vec<u8> {
    let mut w = Writer::default();
    // Token 0 is never a property name: a property's element is stored as
    // its token's index negated, and -0 is 0. USD puts ";-)" there; the
    // root's element is the empty token.
    w.token(";-)");
    w.token("");
    w.path("/");
    let mut out = vec![0u8; 88];
    let mut sets = Vec::new();
    let mut spec_rows = Vec::with_capacity(specs.len());
    for spec in specs {
        let path = w.path(&spec.path);
        let set = sets.len() as u32;
        for (name, value) in &spec.fields {
            let name = w.token(name);
            let rep = w.value(value, &mut out);
            sets.push(w.fields.len() as u32);
            w.fields.push((name, rep));
        }
        sets.push(END);
        spec_rows.push((path, set, spec.kind as u32));
    }
    let mut toc = Vec::new();
    let mut section = |name: &str, out: &mut Vec<u8>, body: Vec<u8>| {
        toc.push((name.to_string(), out.len() as u64, body.len() as u64));
        out.extend(body);
    };
    section("TOKENS", &mut out, w.tokens_section());
    section("STRINGS", &mut out, w.strings_section());
    section("FIELDS", &mut out, w.fields_section());
    let mut body = (sets.len() as u64).to_le_bytes().to_vec();
    blob(&mut body, &encode_ints(&sets.iter().map(|&s| s as i32).collect::<Vec<_>>()));
    section("FIELDSETS", &mut out, body);
    section("PATHS", &mut out, w.paths.section());
    let mut body = (spec_rows.len() as u64).to_le_bytes().to_vec();
    for column in 0..3 {
        let v: Vec<i32> = spec_rows.iter().map(|r| [r.0, r.1, r.2][column] as i32).collect();
        blob(&mut body, &encode_ints(&v));
    }
    section("SPECS", &mut out, body);
    let toc_at = out.len() as u64;
    out.extend((toc.len() as u64).to_le_bytes());
    for (name, start, size) in &toc {
        let mut n = [0u8; 16];
        n[..name.len()].copy_from_slice(name.as_bytes());
        out.extend(n);
        out.extend(start.to_le_bytes());
        out.extend(size.to_le_bytes());
    }
    out[..8].copy_from_slice(b"PXR-USDC");
    out[8..16].copy_from_slice(&[0, 8, 0, 0, 0, 0, 0, 0]);
    out[16..24].copy_from_slice(&toc_at.to_le_bytes());
    out
}

#[derive(Default)]
struct Writer {
    tokens: Vec<String>,
    token_index: HashMap<String, u32>,
    strings: Vec<u32>,
    string_index: HashMap<u32, u32>,
    fields: Vec<(u32, u64)>,
    paths: Paths,
}

impl Writer {
    fn token(&mut self, t: &str) -> u32 {
        if let Some(&i) = self.token_index.get(t) {
            return i;
        }
        let i = self.tokens.len() as u32;
        self.tokens.push(t.to_string());
        self.token_index.insert(t.to_string(), i);
        i
    }

    fn string(&mut self, s: &str) -> u32 {
        let t = self.token(s);
        let next = self.strings.len() as u32;
        let i = *self.string_index.entry(t).or_insert(next);
        if i == next {
            self.strings.push(t);
        }
        i
    }

    /// The value's 64-bit descriptor; what does not fit in it goes to `out`.
    fn value(&mut self, v: &Value, out: &mut Vec<u8>) -> u64 {
        let inline = |t: u64, payload: u64| INLINED | (t << 48) | payload;
        let at = |t: u64, out: &Vec<u8>| (t << 48) | out.len() as u64;
        match v {
            Value::Token(t) => inline(ty::TOKEN, self.token(t) as u64),
            Value::Bool(b) => inline(ty::BOOL, *b as u64),
            Value::Float(f) => inline(ty::FLOAT, f.to_bits() as u64),
            Value::Double(d) => {
                let rep = at(ty::DOUBLE, out);
                out.extend(d.to_le_bytes());
                rep
            }
            Value::String(s) => inline(ty::STRING, self.string(s) as u64),
            Value::Asset(a) => inline(ty::ASSET, self.token(a) as u64),
            Value::Vec3f(v) => {
                let rep = at(ty::VEC3F, out);
                v.iter().for_each(|x| out.extend(x.to_le_bytes()));
                rep
            }
            Value::Def => inline(ty::SPECIFIER, 0),
            Value::Uniform(u) => inline(ty::VARIABILITY, *u as u64),
            Value::Ints(v) => ARRAY | ints(v, out),
            Value::Vec2fs(v) => ARRAY | floats(ty::VEC2F, v.as_flattened(), v.len(), out),
            Value::Vec3fs(v) => ARRAY | floats(ty::VEC3F, v.as_flattened(), v.len(), out),
            Value::Tokens(list) => {
                let rep = at(ty::TOKEN_VECTOR, out);
                let ids: Vec<u32> = list.iter().map(|t| self.token(t)).collect();
                counted(out, &ids);
                rep
            }
            Value::PrependTokens(list) => {
                let rep = at(ty::TOKEN_LIST_OP, out);
                let ids: Vec<u32> = list.iter().map(|t| self.token(t)).collect();
                out.push(0x20); // has prepended items
                counted(out, &ids);
                rep
            }
            Value::Paths(list) => {
                let rep = at(ty::PATH_LIST_OP, out);
                let ids: Vec<u32> = list.iter().map(|p| self.path(p)).collect();
                out.push(0x03); // explicit, with explicit items
                counted(out, &ids);
                rep
            }
        }
    }

    fn tokens_section(&self) -> Vec<u8> {
        let text: Vec<u8> = self.tokens.iter().flat_map(|t| t.bytes().chain([0])).collect();
        let packed = fast_compress(&text);
        let mut body = Vec::with_capacity(24 + packed.len());
        for n in [self.tokens.len(), text.len(), packed.len()] {
            body.extend((n as u64).to_le_bytes());
        }
        body.extend(packed);
        body
    }

    fn strings_section(&self) -> Vec<u8> {
        let mut body = Vec::new();
        counted(&mut body, &self.strings);
        body
    }

    fn fields_section(&self) -> Vec<u8> {
        let mut body = (self.fields.len() as u64).to_le_bytes().to_vec();
        blob(&mut body, &encode_ints(&self.fields.iter().map(|f| f.0 as i32).collect::<Vec<_>>()));
        let reps: Vec<u8> = self.fields.iter().flat_map(|f| f.1.to_le_bytes()).collect();
        let packed = fast_compress(&reps);
        body.extend((packed.len() as u64).to_le_bytes());
        body.extend(packed);
        body
    }
}

/// A `u64` count, then the `u32`s.
fn counted(out: &mut Vec<u8>, v: &[u32]) {
    out.extend((v.len() as u64).to_le_bytes());
    v.iter().for_each(|x| out.extend(x.to_le_bytes()));
}

/// An `int[]`: its count, then the values delta-coded and compressed (16
/// or more) or raw. Returns the descriptor without the array bit.
fn ints(v: &[i32], out: &mut Vec<u8>) -> u64 {
    if v.is_empty() {
        return ty::INT << 48;
    }
    let rep = (ty::INT << 48) | out.len() as u64;
    out.extend((v.len() as u64).to_le_bytes());
    if v.len() < MIN_COMPRESSED {
        v.iter().for_each(|x| out.extend(x.to_le_bytes()));
        return rep;
    }
    blob(out, &encode_ints(v));
    rep | COMPRESSED
}

/// A vector array (`float2[]`, `float3[]`), raw, on 8 bytes as USD puts it.
fn floats(t: u64, flat: &[f32], n: usize, out: &mut Vec<u8>) -> u64 {
    if n == 0 {
        return t << 48;
    }
    out.resize(out.len().next_multiple_of(8), 0);
    let rep = (t << 48) | out.len() as u64;
    out.extend((n as u64).to_le_bytes());
    out.reserve(4 * flat.len());
    flat.iter().for_each(|x| out.extend(x.to_le_bytes()));
    rep
}

/// A compressed block as the sections hold it: its size, then the bytes.
fn blob(out: &mut Vec<u8>, data: &[u8]) {
    let packed = fast_compress(data);
    out.extend((packed.len() as u64).to_le_bytes());
    out.extend(packed);
}

/// USD's `TfFastCompression` of less than 2 GB: a zero chunk count, then one
/// LZ4 block.
fn fast_compress(data: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8];
    out.extend(lz4_flex::block::compress(data));
    out
}

/// USD's integer coding: each value's difference from the one before (the
/// first's from 0), the most frequent difference as a 32-bit common value,
/// a 2-bit code per value (0 the common value, then 8, 16 or 32 bits;
/// first value in a byte's low bits), and the differences that are not the
/// common value at the width their code says.
pub fn encode_ints(v: &[i32]) -> Vec<u8> {
    if v.is_empty() {
        return Vec::new();
    }
    let mut prev = 0i32;
    let deltas: Vec<i32> = v
        .iter()
        .map(|&x| {
            let d = x.wrapping_sub(prev);
            prev = x;
            d
        })
        .collect();
    let mut counts: HashMap<i32, usize> = HashMap::new();
    deltas.iter().for_each(|&d| *counts.entry(d).or_default() += 1);
    // The most frequent, the larger on a tie (as USD does, so its bytes match ours).
    let common = counts.iter().max_by_key(|&(&d, &c)| (c, d)).map(|(&d, _)| d).unwrap_or(0);
    let mut out = common.to_le_bytes().to_vec();
    let codes_at = out.len();
    out.resize(codes_at + (2 * deltas.len()).div_ceil(8), 0);
    for (i, &d) in deltas.iter().enumerate() {
        let code: u8 = if d == common {
            0
        } else if i8::try_from(d).is_ok() {
            out.push(d as i8 as u8);
            1
        } else if i16::try_from(d).is_ok() {
            out.extend((d as i16).to_le_bytes());
            2
        } else {
            out.extend(d.to_le_bytes());
            3
        };
        out[codes_at + i / 4] |= code << (2 * (i % 4));
    }
    out
}

/// The path table: every path a spec or a value names, with its ancestors,
/// numbered in order of first use.
#[derive(Default)]
struct Paths {
    index: HashMap<String, u32>,
    /// Per path: its parent's index and its last element's token (negated
    /// for a property).
    nodes: Vec<(Option<u32>, i32)>,
}

impl Writer {
    /// The path's index, its ancestors' and its elements' tokens added.
    fn path(&mut self, path: &str) -> u32 {
        if let Some(&i) = self.paths.index.get(path) {
            return i;
        }
        let node = if path == "/" {
            (None, self.token("") as i32)
        } else {
            let k = path.rfind(['/', '.']).unwrap_or_else(|| panic!("not an absolute path: {path}"));
            let parent = self.path(if k == 0 { "/" } else { &path[..k] });
            let token = self.token(&path[k + 1..]) as i32;
            (Some(parent), if path.as_bytes()[k] == b'.' { -token } else { token })
        };
        let i = self.paths.nodes.len() as u32;
        self.paths.nodes.push(node);
        self.paths.index.insert(path.to_string(), i);
        i
    }
}

impl Paths {
    /// USD's compressed encoding: the tree walked depth first, each entry
    /// its path's index, its element's token and where its next sibling
    /// is: -2 none, -1 none but children follow, 0 the next entry, n > 0
    /// children follow and the sibling is n entries on (the subtree's size).
    fn section(&self) -> Vec<u8> {
        let n = self.nodes.len();
        let mut children: Vec<Vec<u32>> = vec![Vec::new(); n];
        for (i, (parent, _)) in self.nodes.iter().enumerate() {
            if let Some(p) = parent {
                children[*p as usize].push(i as u32);
            }
        }
        let mut size = vec![1usize; n];
        // A child is numbered after its parent, so backwards sums subtrees.
        for i in (0..n).rev() {
            if let Some(p) = self.nodes[i].0 {
                size[p as usize] += size[i];
            }
        }
        let (mut ids, mut elements, mut jumps) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
        let mut stack = vec![(0u32, false)];
        while let Some((node, sibling)) = stack.pop() {
            ids.push(node as i32);
            elements.push(self.nodes[node as usize].1);
            let kids = &children[node as usize];
            jumps.push(match (kids.is_empty(), sibling) {
                (true, false) => -2,
                (true, true) => 0,
                (false, false) => -1,
                (false, true) => size[node as usize] as i32,
            });
            for (j, &c) in kids.iter().enumerate().rev() {
                stack.push((c, j + 1 < kids.len()));
            }
        }
        let mut body = Vec::new();
        body.extend((n as u64).to_le_bytes());
        body.extend((n as u64).to_le_bytes());
        for column in [&ids, &elements, &jumps] {
            blob(&mut body, &encode_ints(column));
        }
        body
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// USD's decoding of `encode_ints` (`Usd_IntegerCompression`), for `n` values.
    fn decode_ints(b: &[u8], n: usize) -> Vec<i32> {
        if n == 0 {
            return Vec::new();
        }
        let common = i32::from_le_bytes(b[..4].try_into().unwrap());
        let (codes, mut data) = (&b[4..4 + (2 * n).div_ceil(8)], 4 + (2 * n).div_ceil(8));
        let mut prev = 0i32;
        (0..n)
            .map(|i| {
                let d = match (codes[i / 4] >> (2 * (i % 4))) & 3 {
                    0 => common,
                    1 => b[data] as i8 as i32,
                    2 => i16::from_le_bytes(b[data..data + 2].try_into().unwrap()) as i32,
                    _ => i32::from_le_bytes(b[data..data + 4].try_into().unwrap()),
                };
                data += [0, 1, 2, 4][((codes[i / 4] >> (2 * (i % 4))) & 3) as usize];
                prev = prev.wrapping_add(d);
                prev
            })
            .collect()
    }

    #[test]
    fn integers_are_coded_byte_for_byte_as_usd_codes_them() {
        // The path indexes of the specs of a stage USD 26.11 wrote, and the
        // bytes its encoder made of them (before LZ4).
        let v: Vec<i32> =
            (0..16).chain([17, 18, 19, 20, 21, 23, 24, 25, 26, 27, 28, 22, 16, 30, 29, 31, 32, 33]).collect();
        let usd = [
            0x01, 0, 0, 0, 0x01, 0, 0, 0, 0x01, 0x04, 0x40, 0x55, 0x00, 0x00, 0x02, 0x02, 0xfa, 0xfa, 0x0e, 0xff, 0x02,
        ];
        assert_eq!(encode_ints(&v), usd);
        assert!(encode_ints(&[]).is_empty());
    }

    proptest! {
        #[test]
        fn integers_decode_to_what_was_coded(v in prop::collection::vec(any::<i32>(), 0..200),
                                             small in prop::collection::vec(-40_000i32..40_000, 0..200)) {
            for v in [v, small] {
                let coded = encode_ints(&v);
                prop_assert_eq!(decode_ints(&coded, v.len()), v);
            }
        }
    }

    #[test]
    fn compressed_blocks_are_lz4_behind_a_chunk_count() {
        let data: Vec<u8> = (0..5000u32).flat_map(|i| (i / 7).to_le_bytes()).collect();
        let packed = fast_compress(&data);
        assert_eq!(packed[0], 0, "one chunk");
        assert!(packed.len() < data.len() / 3);
        assert_eq!(lz4_flex::block::decompress(&packed[1..], data.len()).unwrap(), data);
    }

    /// The path tree USD walked for the stage above: `/`, `/Model`, its
    /// `Materials` (two children) and `Mesh` (a property), in that order.
    #[test]
    fn paths_are_walked_depth_first_with_their_siblings_jumps() {
        let mut w = Writer::default();
        w.token(";-)");
        for p in ["/", "/Model/Materials/Baked.outputs:surface", "/Model/Materials/Baked/Surface", "/Model/Mesh.points"]
        {
            w.path(p);
        }
        let n = w.paths.nodes.len();
        assert_eq!(n, 8);
        let body = w.paths.section();
        let mut at = 16;
        let mut columns = Vec::new();
        for _ in 0..3 {
            let size = u64::from_le_bytes(body[at..at + 8].try_into().unwrap()) as usize;
            let raw = lz4_flex::block::decompress(&body[at + 9..at + 8 + size], 4 + 2 + 4 * n).unwrap();
            columns.push(decode_ints(&raw, n));
            at += 8 + size;
        }
        assert_eq!(at, body.len());
        let walk: Vec<String> = (0..n)
            .map(|i| {
                let e = columns[1][i];
                let sep = if e < 0 { "." } else { "/" };
                format!("{sep}{} {}", w.tokens[e.unsigned_abs() as usize], columns[2][i])
            })
            .collect();
        // Materials has a sibling (Mesh) 4 entries on: itself, Baked and Baked's two.
        let want = [
            "/ -1",
            "/Model -1",
            "/Materials 4",
            "/Baked -1",
            ".outputs:surface 0",
            "/Surface -2",
            "/Mesh -1",
            ".points -2",
        ];
        assert_eq!(walk, want);
        let m = "/Model/Materials/Baked";
        let order = [
            "/",
            "/Model",
            "/Model/Materials",
            m,
            &format!("{m}.outputs:surface"),
            &format!("{m}/Surface"),
            "/Model/Mesh",
            "/Model/Mesh.points",
        ];
        assert_eq!(columns[0], order.map(|p| w.paths.index[p] as i32));
    }
}
