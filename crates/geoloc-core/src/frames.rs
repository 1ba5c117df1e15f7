//! Per-frame feature records: what `geoloc-rs localize` reads and `geoloc.export_frames` writes.
//!
//! A record holds what the localizer needs of one image: its timestamp (s), its undistorted
//! keypoints (px) with each keypoint's positional σ (px, from the detector scale), its local
//! descriptors (binary u8 or float f32 rows), and the global descriptor when the map retrieves
//! by a network (none for BoW maps).
//!
//! ## Binary stream, version 1 (all integers and floats little-endian)
//!
//! ```text
//! stream header  8 bytes magic "GLFRAMES", u32 version (= 1), u32 reserved (= 0)
//! record         u32 payload length L, then L bytes of payload:
//!                  f64 timestamp
//!                  u32 n (keypoints), u8 descriptor kind (0 binary, 1 float), 3 bytes zero,
//!                  u32 width (bytes or floats per descriptor), u32 g (global length, 0 = none)
//!                  n × (f64 x, f64 y)      keypoints
//!                  n × f64                 pixel σ
//!                  n × width × u8 | f32    descriptors
//!                  g × f32                 global descriptor
//!                  u64 FNV-1a of the payload bytes before it
//! ```
//!
//! L must equal the size implied by n, kind, width and g; sizes are bounded
//! ([`MAX_KEYPOINTS`], [`MAX_DESCRIPTOR_WIDTH`], [`MAX_GLOBAL_DIM`]) and checked before anything is
//! allocated. A length that is self-consistent but larger than the data is refused before
//! allocating too: against the bytes left in a file when the size is known
//! ([`FrameReader::with_size`]), and otherwise (a pipe) by reading the payload in chunks, the
//! buffer growing only with the bytes that actually arrive ([`READ_CHUNK_BYTES`]). So a corrupt
//! length can neither exhaust memory nor hang the reader. Every error names the frame index
//! and the field.
//!
//! ## JSON lines (for debugging)
//!
//! A first line `{"format":"geoloc-frames","version":1}`, then one object per frame:
//! `{"timestamp":t,"keypoints":[[x,y],…],"pixel_sigmas":[…],"descriptor_kind":"binary"|"float",
//! "descriptor_width":w,"descriptors":[[…],…],"global_descriptor":[…]|null}`. Floats are written in the shortest form
//! that reads back to the same bits, so both encodings give identical records.

use std::io::{BufRead, Read, Write};

use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

use crate::checksum::Fnv1a;
use crate::error::{GeolocError, Result};
use crate::matching::DescriptorSet;

/// The magic bytes that open a binary frame stream.
pub const MAGIC: [u8; 8] = *b"GLFRAMES";
/// The stream version this build writes and reads.
pub const VERSION: u32 = 1;
/// Most keypoints a record may hold.
pub const MAX_KEYPOINTS: usize = 1 << 20;
/// Most bytes (binary) or floats (float) per descriptor.
pub const MAX_DESCRIPTOR_WIDTH: usize = 4096;
/// Longest global descriptor.
pub const MAX_GLOBAL_DIM: usize = 1 << 16;
/// The most payload bytes read into memory ahead of the bytes already received, when the
/// stream's size is not known (so a record's length field cannot make the reader allocate
/// more than twice what the stream really holds, plus this).
pub const READ_CHUNK_BYTES: usize = 1 << 20;
/// Bytes of the stream header (magic, version, reserved).
const HEADER_BYTES: usize = 16;
/// Bytes of the fixed part of a payload (timestamp … g).
pub(crate) const FIXED_BYTES: usize = 8 + 4 + 4 + 4 + 4;
/// Bytes of the trailing checksum.
pub(crate) const CHECKSUM_BYTES: usize = 8;

/// One frame's features.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRecord {
    /// Capture time (s).
    pub timestamp: f64,
    /// Undistorted keypoints (px).
    pub keypoints: Vec<Vector2<f64>>,
    /// Positional σ of each keypoint (px, from its detector scale): its pixel noise in PnP is
    /// the localizer's `pixel_sigma` × this ([`crate::localizer::Frame::pixel_sigmas`]).
    pub pixel_sigmas: Vec<f64>,
    /// One descriptor per keypoint.
    pub descriptors: DescriptorSet,
    /// The global descriptor, for maps that retrieve by a network.
    pub global: Option<Vec<f32>>,
}

fn frame_error(index: usize, reason: impl std::fmt::Display) -> GeolocError {
    GeolocError::Format { reason: format!("frame {index}: {reason}") }
}

impl FrameRecord {
    /// Checks the record's invariants: counts agree, values finite, σ > 0, sizes bounded.
    ///
    /// # Errors
    /// `Format` naming frame `index` and the field.
    pub fn check(&self, index: usize) -> Result<()> {
        let n = self.keypoints.len();
        if !self.timestamp.is_finite() {
            return Err(frame_error(index, "timestamp is not finite"));
        }
        if n > MAX_KEYPOINTS {
            return Err(frame_error(index, format!("{n} keypoints exceed the limit of {MAX_KEYPOINTS}")));
        }
        if self.pixel_sigmas.len() != n || self.descriptors.len() != n {
            return Err(frame_error(
                index,
                format!(
                    "{n} keypoints but {} pixel_sigmas and {} descriptors",
                    self.pixel_sigmas.len(),
                    self.descriptors.len()
                ),
            ));
        }
        if let Some(i) = self.keypoints.iter().position(|p| !(p.x.is_finite() && p.y.is_finite())) {
            return Err(frame_error(index, format!("keypoints[{i}] is not finite")));
        }
        if let Some(i) = self.pixel_sigmas.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(frame_error(index, format!("pixel_sigmas[{i}] must be finite and > 0")));
        }
        let (_, width) = kind_and_width(&self.descriptors);
        if width == 0 || width > MAX_DESCRIPTOR_WIDTH {
            return Err(frame_error(index, format!("descriptor width {width} is not in 1..={MAX_DESCRIPTOR_WIDTH}")));
        }
        if let DescriptorSet::Float { data, .. } = &self.descriptors
            && let Some(i) = data.iter().position(|v| !v.is_finite())
        {
            return Err(frame_error(index, format!("descriptors[{}] is not finite", i / width)));
        }
        if let Some(g) = &self.global {
            if g.is_empty() || g.len() > MAX_GLOBAL_DIM {
                return Err(frame_error(
                    index,
                    format!("global descriptor length {} is not in 1..={MAX_GLOBAL_DIM}", g.len()),
                ));
            }
            if g.iter().any(|v| !v.is_finite()) {
                return Err(frame_error(index, "global descriptor is not finite"));
            }
        }
        Ok(())
    }
}

fn kind_and_width(d: &DescriptorSet) -> (u8, usize) {
    match d {
        DescriptorSet::Binary { width, .. } => (0, *width),
        DescriptorSet::Float { width, .. } => (1, *width),
    }
}

/// Payload size implied by the fixed fields, or None on overflow.
pub(crate) fn payload_len(n: usize, kind: u8, width: usize, g: usize) -> Option<usize> {
    let descriptor_bytes = if kind == 0 { 1 } else { 4 };
    let per_keypoint = 16 + 8 + width.checked_mul(descriptor_bytes)?;
    FIXED_BYTES.checked_add(n.checked_mul(per_keypoint)?)?.checked_add(g.checked_mul(4)?)?.checked_add(CHECKSUM_BYTES)
}

/// Writes the binary stream header.
///
/// # Errors
/// `Io` when writing fails.
pub fn write_stream_header(out: &mut impl Write) -> Result<()> {
    let mut header = MAGIC.to_vec();
    header.extend(VERSION.to_le_bytes());
    header.extend(0u32.to_le_bytes());
    out.write_all(&header).map_err(io_error)
}

fn io_error(e: std::io::Error) -> GeolocError {
    GeolocError::Io { path: "frame stream".into(), reason: e.to_string() }
}

/// Writes one record (checked first; `index` names it in errors).
///
/// # Errors
/// `Format` for an invalid record, `Io` when writing fails.
pub fn write_record(out: &mut impl Write, record: &FrameRecord, index: usize) -> Result<()> {
    record.check(index)?;
    let n = record.keypoints.len();
    let (kind, width) = kind_and_width(&record.descriptors);
    let g = record.global.as_ref().map_or(0, Vec::len);
    let len = payload_len(n, kind, width, g).ok_or_else(|| frame_error(index, "record too large"))?;
    let len32 = u32::try_from(len).map_err(|_| frame_error(index, format!("record of {len} bytes is too large")))?;
    let mut p = Vec::with_capacity(len);
    p.extend(record.timestamp.to_le_bytes());
    p.extend((n as u32).to_le_bytes());
    p.extend([kind, 0, 0, 0]);
    p.extend((width as u32).to_le_bytes());
    p.extend((g as u32).to_le_bytes());
    p.extend(record.keypoints.iter().flat_map(|k| [k.x.to_le_bytes(), k.y.to_le_bytes()]).flatten());
    p.extend(record.pixel_sigmas.iter().flat_map(|s| s.to_le_bytes()));
    match &record.descriptors {
        DescriptorSet::Binary { data, .. } => p.extend(data),
        DescriptorSet::Float { data, .. } => p.extend(data.iter().flat_map(|v| v.to_le_bytes())),
    }
    p.extend(record.global.iter().flatten().flat_map(|v| v.to_le_bytes()));
    let mut h = Fnv1a::new();
    h.update(&p);
    p.extend(h.finish().to_le_bytes());
    debug_assert_eq!(p.len(), len);
    out.write_all(&len32.to_le_bytes()).and_then(|()| out.write_all(&p)).map_err(io_error)
}

/// Reads a binary frame stream record by record.
pub struct FrameReader<R: Read> {
    input: R,
    next_index: usize,
    done: bool,
    /// Bytes left in the input, when its size is known.
    remaining: Option<u64>,
}

impl<R: Read> FrameReader<R> {
    /// Reads and checks the stream header; the input's size is not known (a pipe), so record
    /// payloads are read in chunks ([`READ_CHUNK_BYTES`]).
    ///
    /// # Errors
    /// `Format` when the input is not a frame stream of this version.
    pub fn new(input: R) -> Result<Self> {
        Self::open(input, None)
    }

    /// As [`FrameReader::new`] for an input of exactly `size_bytes` bytes (a file's length):
    /// a record whose length field claims more than the bytes left is refused before anything
    /// is allocated or read.
    ///
    /// # Errors
    /// As [`FrameReader::new`].
    pub fn with_size(input: R, size_bytes: u64) -> Result<Self> {
        Self::open(input, Some(size_bytes))
    }

    fn open(mut input: R, size_bytes: Option<u64>) -> Result<Self> {
        let mut header = [0u8; HEADER_BYTES];
        read_exact_or(&mut input, &mut header).map_err(|got| GeolocError::Format {
            reason: format!("frame stream header truncated ({got} of 16 bytes)"),
        })?;
        if header[..8] != MAGIC {
            return Err(GeolocError::Format { reason: "not a geoloc frame stream (bad magic bytes)".into() });
        }
        let version = u32::from_le_bytes(header[8..12].try_into().expect("invariant: 4 bytes"));
        if version != VERSION {
            return Err(GeolocError::Format {
                reason: format!("frame stream version {version} is not supported (this build reads {VERSION})"),
            });
        }
        if header[12..16] != [0; 4] {
            return Err(GeolocError::Format { reason: "frame stream header: reserved bytes are not zero".into() });
        }
        let remaining = size_bytes.map(|n| n.saturating_sub(HEADER_BYTES as u64));
        Ok(Self { input, next_index: 0, done: false, remaining })
    }

    /// The next record, `None` at a clean end of stream (between records).
    ///
    /// # Errors
    /// `Format` naming the frame index: truncated, inconsistent sizes, bad checksum, invalid
    /// values. After an error the reader stops.
    pub fn next_record(&mut self) -> Result<Option<FrameRecord>> {
        if self.done {
            return Ok(None);
        }
        let index = self.next_index;
        let result = self.read_record(index);
        match &result {
            Ok(Some(_)) => self.next_index += 1,
            _ => self.done = true,
        }
        result
    }

    fn read_record(&mut self, index: usize) -> Result<Option<FrameRecord>> {
        let mut len = [0u8; 4];
        match read_exact_or(&mut self.input, &mut len) {
            Ok(()) => {}
            Err(0) => return Ok(None),
            Err(got) => return Err(frame_error(index, format!("truncated length field ({got} of 4 bytes)"))),
        }
        let len = u32::from_le_bytes(len) as usize;
        if len < FIXED_BYTES + CHECKSUM_BYTES {
            return Err(frame_error(index, format!("payload length {len} is too small")));
        }
        if let Some(left) = self.remaining.map(|r| r.saturating_sub(4))
            && len as u64 > left
        {
            return Err(frame_error(
                index,
                format!("payload length field claims {len} bytes, but only {left} are left in the stream"),
            ));
        }
        let mut fixed = [0u8; FIXED_BYTES];
        read_exact_or(&mut self.input, &mut fixed).map_err(|got| truncated(index, got, len))?;
        let u32_at = |o: usize| u32::from_le_bytes(fixed[o..o + 4].try_into().expect("invariant: 4 bytes")) as usize;
        let (n, kind, width, g) = (u32_at(8), fixed[12], u32_at(16), u32_at(20));
        check_sizes(index, n, kind, &fixed[13..16], width, g)?;
        let expected = payload_len(n, kind, width, g).ok_or_else(|| frame_error(index, "sizes overflow"))?;
        if expected != len {
            return Err(frame_error(index, format!("payload length {len} does not match its sizes ({expected})")));
        }
        let rest =
            read_growing(&mut self.input, len - FIXED_BYTES).map_err(|got| truncated(index, FIXED_BYTES + got, len))?;
        self.remaining = self.remaining.map(|r| r.saturating_sub(4 + len as u64));
        let (body, sum) = rest.split_at(rest.len() - CHECKSUM_BYTES);
        let mut h = Fnv1a::new();
        h.update(&fixed);
        h.update(body);
        if h.finish().to_le_bytes() != sum {
            return Err(frame_error(index, "checksum mismatch (corrupt record)"));
        }
        let record = decode_body(&fixed, body, n, kind, width, g);
        record.check(index)?;
        Ok(Some(record))
    }
}

impl<R: Read> Iterator for FrameReader<R> {
    type Item = Result<FrameRecord>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_record().transpose()
    }
}

fn truncated(index: usize, got: usize, len: usize) -> GeolocError {
    frame_error(index, format!("truncated record ({got} of {len} payload bytes)"))
}

fn check_sizes(index: usize, n: usize, kind: u8, reserved: &[u8], width: usize, g: usize) -> Result<()> {
    if kind > 1 {
        return Err(frame_error(index, format!("descriptor kind {kind} is not 0 (binary) or 1 (float)")));
    }
    if reserved.iter().any(|&b| b != 0) {
        return Err(frame_error(index, "reserved bytes are not zero"));
    }
    if n > MAX_KEYPOINTS {
        return Err(frame_error(index, format!("{n} keypoints exceed the limit of {MAX_KEYPOINTS}")));
    }
    if width == 0 || width > MAX_DESCRIPTOR_WIDTH {
        return Err(frame_error(index, format!("descriptor width {width} is not in 1..={MAX_DESCRIPTOR_WIDTH}")));
    }
    if g > MAX_GLOBAL_DIM {
        return Err(frame_error(index, format!("global descriptor length {g} exceeds {MAX_GLOBAL_DIM}")));
    }
    Ok(())
}

fn decode_body(fixed: &[u8], body: &[u8], n: usize, kind: u8, width: usize, g: usize) -> FrameRecord {
    fn f64s(b: &[u8]) -> impl Iterator<Item = f64> + '_ {
        b.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("invariant: 8 bytes")))
    }
    fn f32s(b: &[u8]) -> Vec<f32> {
        b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("invariant: 4 bytes"))).collect()
    }
    let timestamp = f64::from_le_bytes(fixed[..8].try_into().expect("invariant: 8 bytes"));
    let (kp, rest) = body.split_at(16 * n);
    let (sig, rest) = rest.split_at(8 * n);
    let descriptor_bytes = if kind == 0 { width * n } else { 4 * width * n };
    let (desc, glob) = rest.split_at(descriptor_bytes);
    let xy: Vec<f64> = f64s(kp).collect();
    FrameRecord {
        timestamp,
        keypoints: xy.chunks_exact(2).map(|p| Vector2::new(p[0], p[1])).collect(),
        pixel_sigmas: f64s(sig).collect(),
        descriptors: if kind == 0 {
            DescriptorSet::Binary { data: desc.to_vec(), width }
        } else {
            DescriptorSet::Float { data: f32s(desc), width }
        },
        global: (g > 0).then(|| f32s(glob)),
    }
}

/// Reads exactly `want` bytes, growing the buffer only as bytes arrive (by at most
/// max([`READ_CHUNK_BYTES`], what was read so far) at a time), or reports how many bytes were
/// read before the end of input.
fn read_growing(input: &mut impl Read, want: usize) -> std::result::Result<Vec<u8>, usize> {
    let mut out = Vec::new();
    while out.len() < want {
        let start = out.len();
        let step = (want - start).min(start.max(READ_CHUNK_BYTES));
        out.resize(start + step, 0);
        read_exact_or(input, &mut out[start..]).map_err(|got| start + got)?;
    }
    Ok(out)
}

/// Fills `buf` completely, or reports how many bytes were read before the end of input.
fn read_exact_or(input: &mut impl Read, buf: &mut [u8]) -> std::result::Result<(), usize> {
    let mut got = 0;
    while got < buf.len() {
        match input.read(&mut buf[got..]) {
            Ok(0) => return Err(got),
            Ok(k) => got += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(_) => return Err(got),
        }
    }
    Ok(())
}

/// The JSON-lines form of a record.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonRecord {
    timestamp: f64,
    keypoints: Vec<[f64; 2]>,
    pixel_sigmas: Vec<f64>,
    descriptor_kind: String,
    descriptor_width: usize,
    descriptors: Vec<Vec<f64>>,
    global_descriptor: Option<Vec<f32>>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonHeader {
    format: String,
    version: u32,
}

const JSON_FORMAT: &str = "geoloc-frames";

/// Writes the JSON-lines header line.
///
/// # Errors
/// `Io` when writing fails.
pub fn write_json_header(out: &mut impl Write) -> Result<()> {
    let header = JsonHeader { format: JSON_FORMAT.into(), version: VERSION };
    let line = serde_json::to_string(&header).map_err(|e| GeolocError::Format { reason: e.to_string() })?;
    writeln!(out, "{line}").map_err(io_error)
}

/// Writes one record as a JSON line (checked first).
///
/// # Errors
/// `Format` for an invalid record, `Io` when writing fails.
pub fn write_json_record(out: &mut impl Write, record: &FrameRecord, index: usize) -> Result<()> {
    record.check(index)?;
    let (kind, width) = kind_and_width(&record.descriptors);
    let descriptors = match &record.descriptors {
        DescriptorSet::Binary { data, .. } => {
            data.chunks(width).map(|r| r.iter().map(|&b| f64::from(b)).collect()).collect()
        }
        DescriptorSet::Float { data, .. } => {
            data.chunks(width).map(|r| r.iter().map(|&v| f64::from(v)).collect()).collect()
        }
    };
    let json = JsonRecord {
        timestamp: record.timestamp,
        keypoints: record.keypoints.iter().map(|k| [k.x, k.y]).collect(),
        pixel_sigmas: record.pixel_sigmas.clone(),
        descriptor_kind: if kind == 0 { "binary" } else { "float" }.into(),
        descriptor_width: width,
        descriptors,
        global_descriptor: record.global.clone(),
    };
    let line = serde_json::to_string(&json).map_err(|e| frame_error(index, e))?;
    writeln!(out, "{line}").map_err(io_error)
}

/// The longest line of a JSON-lines frame stream (256 MiB): far above a frame of
/// [`MAX_KEYPOINTS`] binary descriptors, and a bound on what one line may allocate (a stream
/// without newlines is refused, not read into memory whole). Larger frames: the binary format.
pub const MAX_JSON_LINE_BYTES: usize = 256 << 20;

/// The lines of `input`, each at most `max` bytes long (without its `\n` / `\r\n`); a longer
/// line is an error and ends the iteration, having read at most `max + 2` bytes of it.
struct BoundedLines<R> {
    input: R,
    max: usize,
    done: bool,
}

impl<R: BufRead> Iterator for BoundedLines<R> {
    type Item = std::io::Result<String>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let mut buf = Vec::new();
        let limit = self.max as u64 + 2; // the line and its "\r\n"
        match self.input.by_ref().take(limit).read_until(b'\n', &mut buf) {
            Err(e) => {
                self.done = true;
                Some(Err(e))
            }
            Ok(0) => None,
            Ok(_) => {
                let ended = buf.last() == Some(&b'\n');
                if ended {
                    buf.pop();
                    if buf.last() == Some(&b'\r') {
                        buf.pop();
                    }
                }
                if buf.len() > self.max || (!ended && buf.len() as u64 == limit) {
                    self.done = true;
                    let message = format!("a line longer than {} bytes (use the binary format)", self.max);
                    return Some(Err(std::io::Error::new(std::io::ErrorKind::InvalidData, message)));
                }
                Some(String::from_utf8(buf).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e)))
            }
        }
    }
}

/// Reads a JSON-lines frame stream (header line first).
///
/// # Errors
/// `Format` naming the frame index (or the header) for malformed lines or invalid records.
pub fn read_json_records(input: impl BufRead) -> impl Iterator<Item = Result<FrameRecord>> {
    let mut lines = BoundedLines { input, max: MAX_JSON_LINE_BYTES, done: false }.enumerate();
    let header = match lines.next() {
        None => Err(GeolocError::Format { reason: "empty JSON frame stream (no header line)".into() }),
        Some((_, line)) => line.map_err(io_error).and_then(|l| check_json_header(&l)),
    };
    let mut failed = header.is_err();
    let first = header.err().map(Err);
    first.into_iter().chain(lines.filter(|(_, l)| l.as_ref().map_or(true, |s| !s.trim().is_empty())).map_while(
        move |(line_no, line)| {
            if failed {
                return None;
            }
            let result = line.map_err(io_error).and_then(|l| parse_json_record(&l, line_no - 1));
            failed = result.is_err();
            Some(result)
        },
    ))
}

fn check_json_header(line: &str) -> Result<()> {
    let header: JsonHeader = serde_json::from_str(line)
        .map_err(|e| GeolocError::Format { reason: format!("JSON frame stream header: {e}") })?;
    if header.format != JSON_FORMAT || header.version != VERSION {
        return Err(GeolocError::Format {
            reason: format!(
                "JSON frame stream {:?} version {} is not {JSON_FORMAT:?} {VERSION}",
                header.format, header.version
            ),
        });
    }
    Ok(())
}

fn parse_json_record(line: &str, index: usize) -> Result<FrameRecord> {
    let json: JsonRecord = serde_json::from_str(line).map_err(|e| frame_error(index, e))?;
    let width = json.descriptor_width;
    if json.descriptors.iter().any(|r| r.len() != width) {
        return Err(frame_error(index, "descriptor rows differ in length"));
    }
    let flat = json.descriptors.iter().flatten().copied();
    let descriptors = match json.descriptor_kind.as_str() {
        "binary" => {
            let data: Option<Vec<u8>> =
                flat.map(|v| (v.fract() == 0.0 && (0.0..=255.0).contains(&v)).then_some(v as u8)).collect();
            DescriptorSet::Binary {
                data: data.ok_or_else(|| frame_error(index, "binary descriptors must be bytes"))?,
                width,
            }
        }
        "float" => DescriptorSet::Float { data: flat.map(|v| v as f32).collect(), width },
        other => return Err(frame_error(index, format!("descriptor_kind {other:?} is not \"binary\" or \"float\""))),
    };
    let record = FrameRecord {
        timestamp: json.timestamp,
        keypoints: json.keypoints.iter().map(|k| Vector2::new(k[0], k[1])).collect(),
        pixel_sigmas: json.pixel_sigmas,
        descriptors,
        global: json.global_descriptor,
    };
    record.check(index)?;
    Ok(record)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    fn record(rng: &mut SplitMix64, n: usize, binary: bool, global: bool, t: f64) -> FrameRecord {
        let keypoints = (0..n).map(|_| Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0))).collect();
        let pixel_sigmas = (0..n).map(|i| 1.2f64.powi((i % 8) as i32)).collect();
        let descriptors = if binary {
            DescriptorSet::Binary { data: (0..n * 32).map(|_| (rng.next_u64() & 0xff) as u8).collect(), width: 32 }
        } else {
            DescriptorSet::Float { data: (0..n * 128).map(|_| rng.uniform_in(-1.0, 1.0) as f32).collect(), width: 128 }
        };
        let global = global.then(|| (0..16).map(|_| rng.uniform_in(-1.0, 1.0) as f32).collect());
        FrameRecord { timestamp: t, keypoints, pixel_sigmas, descriptors, global }
    }

    fn stream(records: &[FrameRecord]) -> Vec<u8> {
        let mut out = Vec::new();
        write_stream_header(&mut out).expect("in memory");
        for (i, r) in records.iter().enumerate() {
            write_record(&mut out, r, i).expect("valid record");
        }
        out
    }

    fn sample() -> Vec<FrameRecord> {
        let mut rng = SplitMix64::new(11);
        vec![
            record(&mut rng, 5, true, false, 0.0),
            record(&mut rng, 0, true, false, 0.033),
            record(&mut rng, 3, false, true, 0.066),
        ]
    }

    fn read_all(bytes: &[u8]) -> Result<Vec<FrameRecord>> {
        FrameReader::new(bytes)?.collect()
    }

    #[test]
    fn binary_and_json_round_trip_bit_exactly() {
        let records = sample();
        assert_eq!(read_all(&stream(&records)).expect("reads back"), records);
        let mut json = Vec::new();
        write_json_header(&mut json).expect("in memory");
        for (i, r) in records.iter().enumerate() {
            write_json_record(&mut json, r, i).expect("valid record");
        }
        let back: Vec<FrameRecord> = read_json_records(json.as_slice()).collect::<Result<_>>().expect("reads back");
        assert_eq!(back, records);
    }

    #[test]
    fn layout_matches_the_documented_format() {
        // An independent decoding of the documented layout for the first record.
        let records = sample();
        let bytes = stream(&records);
        assert_eq!(&bytes[..8], b"GLFRAMES");
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().expect("4")), 1);
        let len = u32::from_le_bytes(bytes[16..20].try_into().expect("4")) as usize;
        assert_eq!(len, 24 + 5 * (16 + 8 + 32) + 8);
        let p = &bytes[20..20 + len];
        assert_eq!(f64::from_le_bytes(p[..8].try_into().expect("8")).to_bits(), 0.0f64.to_bits());
        assert_eq!(u32::from_le_bytes(p[8..12].try_into().expect("4")), 5);
        let x0 = f64::from_le_bytes(p[24..32].try_into().expect("8"));
        assert_eq!(x0.to_bits(), records[0].keypoints[0].x.to_bits());
    }

    #[test]
    fn every_truncation_is_an_error_naming_the_frame_or_a_clean_end() {
        let records = sample();
        let bytes = stream(&records);
        let mut boundaries = vec![16];
        let mut at = 16;
        while at < bytes.len() {
            at += 4 + u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4")) as usize;
            boundaries.push(at);
        }
        for cut in 0..bytes.len() {
            let result = read_all(&bytes[..cut]);
            if let Some(k) = boundaries.iter().position(|&b| b == cut) {
                assert_eq!(result.expect("clean end between records"), records[..k], "cut {cut}");
            } else {
                let err = result.expect_err("a truncated stream is refused");
                let text = err.to_string();
                assert!(matches!(err, GeolocError::Format { .. }), "cut {cut}: {err:?}");
                if cut >= 16 {
                    assert!(text.starts_with("frame "), "cut {cut}: {text}");
                }
            }
        }
    }

    #[test]
    fn random_flips_and_truncations_never_panic_or_pass_silently() {
        let records = sample();
        let bytes = stream(&records);
        let mut rng = SplitMix64::new(5);
        for case in 0..2000 {
            let mut bad = bytes.clone();
            let flips = 1 + (rng.next_u64() % 3) as usize;
            for _ in 0..flips {
                let i = (rng.next_u64() % bad.len() as u64) as usize;
                bad[i] ^= 1 << (rng.next_u64() % 8);
            }
            if case % 2 == 0 {
                bad.truncate((rng.next_u64() % bad.len() as u64) as usize);
            }
            if bad == bytes {
                continue; // two flips of the same bit cancel
            }
            if let Ok(read) = read_all(&bad) {
                // Only a prefix of the true records may come back (a cut between records).
                assert!(read.len() < records.len() && read == records[..read.len()], "case {case}");
            }
        }
    }

    #[test]
    fn huge_declared_sizes_are_refused_before_allocating() {
        let mut bytes = Vec::new();
        write_stream_header(&mut bytes).expect("in memory");
        bytes.extend(u32::MAX.to_le_bytes());
        bytes.extend(0.0f64.to_le_bytes());
        bytes.extend(u32::MAX.to_le_bytes()); // n
        bytes.extend([0, 0, 0, 0]);
        bytes.extend(32u32.to_le_bytes());
        bytes.extend(0u32.to_le_bytes());
        let err = read_all(&bytes).expect_err("n too large");
        assert!(err.to_string().contains("frame 0") && err.to_string().contains("exceed the limit"), "{err}");
    }

    #[test]
    fn a_self_consistent_length_beyond_the_data_is_refused_before_allocating() {
        let (bytes, len) = crate::testing::huge_frame_record_claim();
        // the size known (a file): refused from the length field, before reading the payload
        let err = FrameReader::with_size(bytes.as_slice(), bytes.len() as u64)
            .expect("header intact")
            .next_record()
            .expect_err("claims more than the file holds");
        assert_eq!(
            err.to_string(),
            format!("frame 0: payload length field claims {len} bytes, but only 24 are left in the stream")
        );
        // the size unknown (a pipe): the buffer grows with what arrives, so the end of input
        // is reached after at most READ_CHUNK_BYTES of buffer, not a 4 GB allocation
        let mut counted = CountingReader { input: bytes.as_slice(), largest_buffer: 0 };
        let err = FrameReader::new(&mut counted).expect("header intact").next_record().expect_err("truncated");
        assert_eq!(err.to_string(), format!("frame 0: truncated record (24 of {len} payload bytes)"));
        assert!(counted.largest_buffer <= READ_CHUNK_BYTES, "asked to fill {} bytes", counted.largest_buffer);
    }

    /// Bounded lines are std's `lines()` for every input whose lines fit (LF, CRLF, a last
    /// line without newline, blank lines, invalid UTF-8), across the bound's edges.
    #[test]
    fn bounded_lines_match_std_lines_below_the_bound() {
        let inputs: [&[u8]; 8] =
            [b"", b"a", b"a\n", b"a\r\nbb\n\nccc", b"\n\n", b"abcd\nabcde\r\n", b"ab\xffc\nok\n", b"\r\n"];
        for input in inputs {
            let ours: Vec<_> = BoundedLines { input, max: 5, done: false }.map(|l| l.map_err(|e| e.kind())).collect();
            let std: Vec<_> = input.lines().map(|l| l.map_err(|e| e.kind())).collect();
            assert_eq!(ours, std, "{:?}", String::from_utf8_lossy(input));
        }
    }

    /// A line over the bound is refused after reading at most bound + 2 bytes of it, with or
    /// without a newline; exactly the bound (with CRLF) is read.
    #[test]
    fn a_line_over_the_bound_is_refused_without_reading_it_whole() {
        let exact = b"12345\r\nnext";
        let lines: Vec<_> = BoundedLines { input: exact.as_slice(), max: 5, done: false }.collect();
        assert_eq!(lines.into_iter().map(|l| l.expect("fits")).collect::<Vec<_>>(), ["12345", "next"]);
        for input in [b"123456\n".as_slice(), b"1234567890".as_slice(), b"123456".as_slice()] {
            let mut counted = CountingReader { input, largest_buffer: 0 };
            let mut lines =
                BoundedLines { input: std::io::BufReader::with_capacity(4, &mut counted), max: 5, done: false };
            let err = lines.next().expect("one item").expect_err("too long");
            assert!(err.to_string().contains("longer than 5 bytes"), "{err}");
            assert!(lines.next().is_none());
        }
        // an endless stream without a newline: refused at the bound, not read forever
        let endless = std::io::BufReader::new(std::io::repeat(b'x'));
        let err = read_json_records(endless).next().expect("one item").expect_err("endless header");
        assert!(err.to_string().contains(&format!("longer than {MAX_JSON_LINE_BYTES} bytes")), "{err}");
    }

    /// A reader that records the largest buffer it was asked to fill.
    struct CountingReader<'a> {
        input: &'a [u8],
        largest_buffer: usize,
    }

    impl Read for CountingReader<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            self.largest_buffer = self.largest_buffer.max(buf.len());
            self.input.read(buf)
        }
    }

    #[test]
    fn a_known_size_reads_every_record_and_stops_cleanly() {
        let records = sample();
        let bytes = stream(&records);
        let back: Vec<FrameRecord> = FrameReader::with_size(bytes.as_slice(), bytes.len() as u64)
            .expect("header")
            .collect::<Result<_>>()
            .expect("reads back");
        assert_eq!(back, records);
        // a size one byte short: the last record's claim exceeds what is left
        let err = FrameReader::with_size(bytes.as_slice(), bytes.len() as u64 - 1)
            .expect("header")
            .collect::<Result<Vec<_>>>()
            .expect_err("short by one");
        assert!(err.to_string().starts_with("frame 2: payload length field claims"), "{err}");
    }

    #[test]
    fn invalid_records_name_frame_and_field() {
        let mut rng = SplitMix64::new(3);
        let mut r = record(&mut rng, 4, true, false, 1.0);
        r.keypoints[2].x = f64::NAN;
        let err = write_record(&mut Vec::new(), &r, 7).expect_err("NaN keypoint");
        assert_eq!(err.to_string(), "frame 7: keypoints[2] is not finite");
        let mut r = record(&mut rng, 4, true, false, 1.0);
        r.pixel_sigmas[1] = 0.0;
        let err = write_record(&mut Vec::new(), &r, 3).expect_err("zero sigma");
        assert!(err.to_string().starts_with("frame 3: pixel_sigmas[1]"), "{err}");
        let err = read_all(b"GLFRAMES\x02\0\0\0\0\0\0\0").expect_err("other version");
        assert!(err.to_string().contains("version 2 is not supported"), "{err}");
        let bad_json = "{\"format\":\"geoloc-frames\",\"version\":1}\n{\"timestamp\":1}\n";
        let err = read_json_records(bad_json.as_bytes()).next().expect("one item").expect_err("missing fields");
        assert!(err.to_string().starts_with("frame 0:"), "{err}");
    }
}
