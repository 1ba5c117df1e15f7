//! The `.geoloc` file: named arrays + a JSON header in the **safetensors** format.
//!
//! Layout (the safetensors format, <https://github.com/huggingface/safetensors>):
//! `u64 little-endian header length ‖ JSON header ‖ tensor bytes`. The JSON header lists each
//! tensor's dtype, shape and byte range, plus one `__metadata__` entry `"geoloc"` whose value is
//! a JSON string:
//!
//! ```text
//! {"format":"geoloc-map","version":1,"checksum":"fnv1a64:<16 hex>","header":"<JSON text>"}
//! ```
//!
//! `header` is the map's own JSON (camera, options, estimated noise levels …), kept as text so
//! the checksum covers its exact bytes. The checksum is FNV-1a (64 bit) over the header text and,
//! for every tensor in name order, its name, dtype, shape and bytes: a file cut at any byte, or
//! with any byte flipped, is refused with an error that says which check failed.
//!
//! Writing is atomic ([`crate::files::AtomicFile`]): a temp file of its own in the target's
//! folder, `fsync`, rename over the target, then `fsync` of the folder, so an interrupted save
//! leaves the previous file intact and concurrent saves to one path leave one complete map.
//! Reading refuses anything but a regular file before opening it (a FIFO would block), and
//! checks the header length field against the bytes that follow it before parsing. Reading parses
//! and checks everything before anything is returned (nothing is half-loaded) and never executes
//! code. The same content always gives the same bytes (tensors are sorted by name; the one
//! metadata entry has a fixed layout).

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::checksum::Fnv1a;
use crate::error::{GeolocError, Result};
use crate::files;

/// The value of the `format` field.
pub const FORMAT_NAME: &str = "geoloc-map";
/// The file format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;
/// The safetensors metadata key that holds geoloc's envelope.
const METADATA_KEY: &str = "geoloc";
/// The largest file [`read`] accepts (a map of 100k keyframes × 2000 features is ~10 GB; this
/// guards against reading a wrong, huge file into memory).
pub const MAX_FILE_BYTES: u64 = 16 << 30;

/// The data of one named array, little-endian on disk.
#[derive(Clone, Debug, PartialEq)]
pub enum TensorData {
    /// Bytes (binary descriptors, flags).
    U8(Vec<u8>),
    /// Unsigned 32-bit integers (word ids, indices).
    U32(Vec<u32>),
    /// Signed 64-bit integers (offsets, counts).
    I64(Vec<i64>),
    /// Single precision (float descriptors).
    F32(Vec<f32>),
    /// Double precision (poses, keypoints, covariances).
    F64(Vec<f64>),
}

impl TensorData {
    fn len(&self) -> usize {
        match self {
            Self::U8(v) => v.len(),
            Self::U32(v) => v.len(),
            Self::I64(v) => v.len(),
            Self::F32(v) => v.len(),
            Self::F64(v) => v.len(),
        }
    }

    fn dtype(&self) -> Dtype {
        match self {
            Self::U8(_) => Dtype::U8,
            Self::U32(_) => Dtype::U32,
            Self::I64(_) => Dtype::I64,
            Self::F32(_) => Dtype::F32,
            Self::F64(_) => Dtype::F64,
        }
    }

    fn to_le_bytes(&self) -> Vec<u8> {
        fn bytes<T: Copy, const N: usize>(v: &[T], f: impl Fn(T) -> [u8; N]) -> Vec<u8> {
            v.iter().flat_map(|&x| f(x)).collect()
        }
        match self {
            Self::U8(v) => v.clone(),
            Self::U32(v) => bytes(v, u32::to_le_bytes),
            Self::I64(v) => bytes(v, i64::to_le_bytes),
            Self::F32(v) => bytes(v, f32::to_le_bytes),
            Self::F64(v) => bytes(v, f64::to_le_bytes),
        }
    }

    fn from_le_bytes(dtype: Dtype, data: &[u8], name: &str) -> Result<Self> {
        fn values<T, const N: usize>(data: &[u8], f: impl Fn([u8; N]) -> T) -> Vec<T> {
            data.chunks_exact(N).map(|c| f(c.try_into().expect("invariant: chunks_exact yields N bytes"))).collect()
        }
        Ok(match dtype {
            Dtype::U8 => Self::U8(data.to_vec()),
            Dtype::U32 => Self::U32(values(data, u32::from_le_bytes)),
            Dtype::I64 => Self::I64(values(data, i64::from_le_bytes)),
            Dtype::F32 => Self::F32(values(data, f32::from_le_bytes)),
            Dtype::F64 => Self::F64(values(data, f64::from_le_bytes)),
            other => return Err(format_error(format!("array {name:?} has unsupported dtype {other:?}"))),
        })
    }
}

/// One named array: a shape (row-major) and its data.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// The shape; the product of its entries is the data's length.
    pub shape: Vec<usize>,
    /// The values.
    pub data: TensorData,
}

impl Tensor {
    /// A tensor, checking that `shape` matches the data's length.
    ///
    /// # Errors
    /// `InvalidInput` naming `name` when the shape's product differs from the data's length.
    pub fn new(name: &str, shape: Vec<usize>, data: TensorData) -> Result<Self> {
        let expected = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        if expected != Some(data.len()) {
            return Err(GeolocError::invalid(name, format!("shape {shape:?} does not hold {} values", data.len())));
        }
        Ok(Self { shape, data })
    }
}

/// What a `.geoloc` file holds: the map's JSON header text and its named arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapFile {
    /// The map's JSON header (camera, options, noise estimates …), as text.
    pub header: String,
    /// The arrays, by name (sorted, so the bytes written are deterministic).
    pub tensors: BTreeMap<String, Tensor>,
}

fn format_error(reason: impl Into<String>) -> GeolocError {
    GeolocError::Format { reason: reason.into() }
}

fn io_error(path: &Path, what: &str, e: &std::io::Error) -> GeolocError {
    GeolocError::Io { path: path.display().to_string(), reason: format!("{what}: {e}") }
}

fn checksum<'a>(header: &str, tensors: impl Iterator<Item = (&'a str, Dtype, &'a [usize], &'a [u8])>) -> String {
    let mut h = Fnv1a::new();
    h.field(header.as_bytes());
    for (name, dtype, shape, bytes) in tensors {
        h.field(name.as_bytes());
        h.field(format!("{dtype:?}").as_bytes());
        for &d in shape {
            h.update(&(d as u64).to_le_bytes());
        }
        h.field(bytes);
    }
    format!("fnv1a64:{:016x}", h.finish())
}

#[derive(serde::Serialize, serde::Deserialize)]
struct Envelope {
    format: String,
    version: u32,
    checksum: String,
    header: String,
}

impl MapFile {
    /// The file's bytes (deterministic for equal content).
    ///
    /// # Errors
    /// `Format` if the content cannot be serialized (e.g. a header larger than safetensors allows).
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let raw: Vec<(&str, Dtype, &[usize], Vec<u8>)> = self
            .tensors
            .iter()
            .map(|(name, t)| (name.as_str(), t.data.dtype(), t.shape.as_slice(), t.data.to_le_bytes()))
            .collect();
        let sum = checksum(&self.header, raw.iter().map(|(n, d, s, b)| (*n, *d, *s, b.as_slice())));
        let envelope = Envelope {
            format: FORMAT_NAME.to_owned(),
            version: FORMAT_VERSION,
            checksum: sum,
            header: self.header.clone(),
        };
        let envelope = serde_json::to_string(&envelope).map_err(|e| format_error(e.to_string()))?;
        let views = raw
            .iter()
            .map(|(name, dtype, shape, bytes)| {
                TensorView::new(*dtype, shape.to_vec(), bytes)
                    .map(|v| (*name, v))
                    .map_err(|e| format_error(e.to_string()))
            })
            .collect::<Result<Vec<_>>>()?;
        let metadata = std::collections::HashMap::from([(METADATA_KEY.to_owned(), envelope)]);
        safetensors::serialize(views, Some(metadata)).map_err(|e| format_error(e.to_string()))
    }

    /// Parses and checks a file's bytes; see the module doc for what is checked.
    ///
    /// # Errors
    /// `Format` saying which check failed: not a safetensors file (truncated, corrupt header),
    /// not a geoloc map, another format version, a checksum mismatch.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        if let Some(field) = bytes.first_chunk::<8>() {
            check_header_length(u64::from_le_bytes(*field), bytes.len() as u64)?;
        }
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| format_error(format!("not a valid safetensors file (truncated or corrupt): {e}")))?;
        let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(|e| format_error(e.to_string()))?;
        let envelope = metadata
            .metadata()
            .as_ref()
            .and_then(|m| m.get(METADATA_KEY))
            .ok_or_else(|| format_error("not a geoloc map (no \"geoloc\" metadata entry)"))?;
        let envelope: Envelope =
            serde_json::from_str(envelope).map_err(|e| format_error(format!("corrupt geoloc metadata entry: {e}")))?;
        if envelope.format != FORMAT_NAME {
            return Err(format_error(format!("not a geoloc map (format {:?})", envelope.format)));
        }
        if envelope.version != FORMAT_VERSION {
            return Err(format_error(format!(
                "map format version {} is not supported by this build (it reads version {FORMAT_VERSION}); \
                 rebuild the map with this version",
                envelope.version
            )));
        }
        let mut views: Vec<(String, TensorView<'_>)> = st.tensors();
        views.sort_by(|a, b| a.0.cmp(&b.0));
        let sum = checksum(&envelope.header, views.iter().map(|(n, v)| (n.as_str(), v.dtype(), v.shape(), v.data())));
        if sum != envelope.checksum {
            return Err(format_error(format!(
                "checksum mismatch (stored {}, computed {sum}): the file is corrupt",
                envelope.checksum
            )));
        }
        let mut tensors = BTreeMap::new();
        for (name, view) in views {
            let data = TensorData::from_le_bytes(view.dtype(), view.data(), &name)?;
            tensors.insert(name, Tensor { shape: view.shape().to_vec(), data });
        }
        Ok(Self { header: envelope.header, tensors })
    }

    /// The array called `name`.
    ///
    /// # Errors
    /// `Format` when the file has no such array.
    pub fn tensor(&self, name: &str) -> Result<&Tensor> {
        self.tensors.get(name).ok_or_else(|| format_error(format!("the map has no array {name:?}")))
    }
}

/// Writes `file` to `path` atomically (see [`crate::files::AtomicFile`]: a unique temp file,
/// fsync, rename, folder fsync), so concurrent saves to one path never share a temp file and
/// the target always holds one complete map.
///
/// # Errors
/// `Io` naming the path when the folder does not exist or is not writable, or the disk fails;
/// the previous file at `path`, if any, is then left untouched.
pub fn write(path: &Path, file: &MapFile) -> Result<()> {
    let bytes = file.to_bytes()?;
    files::write_atomic(path, &bytes)
}

/// Reads and checks the file at `path`; see [`MapFile::from_bytes`].
///
/// # Errors
/// `Io` naming the path when the file cannot be read (missing, too large) or is not a regular
/// file (a folder, a FIFO, a device: checked before opening, so a FIFO cannot block the
/// reader); `Format` when it is not a valid geoloc map of this version.
pub fn read(path: &Path) -> Result<MapFile> {
    let (file, len) = files::open_regular(path, "the map")?;
    if len > MAX_FILE_BYTES {
        return Err(GeolocError::Io {
            path: path.display().to_string(),
            reason: format!("{len} bytes is larger than a map may be ({MAX_FILE_BYTES})"),
        });
    }
    let named = |e: GeolocError| match e {
        GeolocError::Format { reason } => GeolocError::Format { reason: format!("{}: {reason}", path.display()) },
        other => other,
    };
    let mut file = file.take(MAX_FILE_BYTES + 1);
    let mut read_more = |bytes: &mut Vec<u8>, limit: u64| {
        (&mut file).take(limit).read_to_end(bytes).map_err(|e| io_error(path, "cannot read the map", &e))
    };
    // the header first: a file that is not a map (a video, a sparse or zero-filled file) is
    // refused from its first bytes, before its whole length is read into memory
    let mut bytes = Vec::new();
    read_more(&mut bytes, 8)?;
    if let Some(field) = bytes.first_chunk::<8>() {
        let claimed = u64::from_le_bytes(*field);
        check_header_length(claimed, len).map_err(named)?;
        read_more(&mut bytes, claimed)?;
        check_array_extent(&bytes[8..], len).map_err(named)?;
    }
    bytes.reserve_exact(usize::try_from(len).unwrap_or(0).saturating_sub(bytes.len()));
    read_more(&mut bytes, u64::MAX)?;
    MapFile::from_bytes(&bytes).map_err(named)
}

/// The largest JSON header [`read`] accepts (bytes): the safetensors crate's own limit.
pub const MAX_HEADER_BYTES: u64 = 100_000_000;

/// The header length field `claimed` of a file of `len` bytes, checked before the header is
/// read: at most [`MAX_HEADER_BYTES`] and within the bytes that follow the field.
fn check_header_length(claimed: u64, len: u64) -> Result<()> {
    let left = len.saturating_sub(8);
    if claimed > left {
        return Err(format_error(format!(
            "header length field claims {claimed} bytes, but only {left} follow it (truncated or corrupt)"
        )));
    }
    if claimed > MAX_HEADER_BYTES {
        return Err(format_error(format!(
            "header length field claims {claimed} bytes, more than a map's header may be ({MAX_HEADER_BYTES})"
        )));
    }
    Ok(())
}

/// Whether the arrays a safetensors `header` (JSON) describes end exactly where a file of
/// `len` bytes ends: the largest `data_offsets` end, plus the 8-byte field and the header, is
/// `len` (the layout safetensors itself requires). Checked before the arrays are read, so a
/// file whose first bytes are not a map header costs its header, not its length.
fn check_array_extent(header: &[u8], len: u64) -> Result<()> {
    let parsed: BTreeMap<String, serde_json::Value> = serde_json::from_slice(header).map_err(|e| {
        format_error(format!("not a valid safetensors file (truncated or corrupt): invalid JSON header: {e}"))
    })?;
    let mut end = 0u64;
    for (name, entry) in parsed.iter().filter(|(name, _)| name.as_str() != "__metadata__") {
        let offsets = entry.get("data_offsets").and_then(serde_json::Value::as_array);
        let bounds: Option<Vec<u64>> = offsets.map(|o| o.iter().filter_map(serde_json::Value::as_u64).collect());
        match bounds.as_deref() {
            Some(&[begin, stop]) if begin <= stop => end = end.max(stop),
            _ => {
                return Err(format_error(format!(
                    "not a valid safetensors file: array {name:?} has no valid data_offsets"
                )));
            }
        }
    }
    let expected = 8 + header.len() as u64 + end;
    if expected != len {
        return Err(format_error(format!(
            "the header describes {expected} bytes but the file holds {len} (truncated, extended or corrupt)"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    fn sample() -> MapFile {
        let mut tensors = BTreeMap::new();
        let t = |name: &str, shape: Vec<usize>, data| Tensor::new(name, shape, data).expect("invariant: sizes agree");
        tensors.insert("poses".into(), t("poses", vec![2, 4, 4], TensorData::F64((0..32).map(f64::from).collect())));
        tensors.insert("descriptors".into(), t("descriptors", vec![3, 4], TensorData::U8((0..12).collect())));
        tensors.insert("words".into(), t("words", vec![5], TensorData::U32(vec![1, 2, 3, 4, u32::MAX])));
        tensors.insert("offsets".into(), t("offsets", vec![3], TensorData::I64(vec![0, -5, i64::MAX])));
        tensors.insert("global".into(), t("global", vec![1, 2], TensorData::F32(vec![0.5, -1e-30])));
        MapFile { header: r#"{"camera":[525.0,525.0,320.0,240.0]}"#.into(), tensors }
    }

    #[test]
    fn round_trips_exactly_and_deterministically() {
        let file = sample();
        let bytes = file.to_bytes().expect("serializes");
        assert_eq!(bytes, file.to_bytes().expect("serializes"), "same content, same bytes");
        assert_eq!(MapFile::from_bytes(&bytes).expect("reads"), file);
    }

    #[test]
    fn is_a_plain_safetensors_file() {
        // An independent reader (the safetensors crate alone) sees our arrays as written.
        let bytes = sample().to_bytes().expect("serializes");
        let st = SafeTensors::deserialize(&bytes).expect("valid safetensors");
        let poses = st.tensor("poses").expect("present");
        assert_eq!(poses.shape(), &[2, 4, 4]);
        assert_eq!(poses.dtype(), Dtype::F64);
        assert_eq!(&poses.data()[8..16], &1.0f64.to_le_bytes());
    }

    #[test]
    fn every_truncation_is_refused() {
        let bytes = sample().to_bytes().expect("serializes");
        for cut in 0..bytes.len() {
            let err = MapFile::from_bytes(&bytes[..cut]).expect_err("a truncated file is refused");
            assert!(matches!(err, GeolocError::Format { .. }), "cut at {cut}: {err:?}");
        }
    }

    #[test]
    fn every_single_byte_flip_is_refused() {
        let bytes = sample().to_bytes().expect("serializes");
        for i in 0..bytes.len() {
            for flip in [0x01u8, 0x80] {
                let mut bad = bytes.clone();
                bad[i] ^= flip;
                let err = MapFile::from_bytes(&bad).expect_err("a corrupted file is refused");
                assert!(matches!(err, GeolocError::Format { .. }), "byte {i} ^ {flip:#x}: {err:?}");
            }
        }
    }

    #[test]
    fn other_versions_and_other_files_are_named() {
        let file = sample();
        let bytes = file.to_bytes().expect("serializes");
        let field = br#"\"version\":1"#;
        let start = bytes.windows(field.len()).position(|w| w == field).expect("version field in the header");
        let mut bad = bytes.clone();
        bad[start + field.len() - 1] = b'9';
        let err = MapFile::from_bytes(&bad).expect_err("other version");
        assert!(err.to_string().contains("version 9 is not supported"), "{err}");
        let plain = safetensors::serialize(Vec::<(&str, TensorView<'_>)>::new(), None).expect("empty file");
        let err = MapFile::from_bytes(&plain).expect_err("not ours");
        assert!(err.to_string().contains("not a geoloc map"), "{err}");
    }

    #[test]
    fn shape_must_match_the_data() {
        let err = Tensor::new("poses", vec![2, 4, 4], TensorData::F64(vec![0.0; 31])).expect_err("31 ≠ 32");
        assert!(matches!(err, GeolocError::InvalidInput { ref name, .. } if name == "poses"), "{err:?}");
    }

    #[test]
    fn write_is_atomic_and_read_names_the_problem() {
        let dir = std::env::temp_dir().join(format!("geoloc-mapfile-{}", std::process::id()));
        fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("scene.geoloc");
        let file = sample();
        write(&path, &file).expect("writes");
        assert_eq!(read(&path).expect("reads back"), file);
        // A failed save (missing folder) leaves nothing behind and names the path.
        let err = write(&dir.join("missing").join("x.geoloc"), &file).expect_err("no such folder");
        assert!(matches!(err, GeolocError::Io { .. }) && err.to_string().contains("missing"), "{err}");
        // Overwriting keeps a valid file at every moment: no temp files remain.
        write(&path, &MapFile { header: "{}".into(), ..file.clone() }).expect("overwrites");
        let leftovers: Vec<_> = fs::read_dir(&dir).expect("list").filter_map(|e| e.ok()).collect();
        assert_eq!(leftovers.len(), 1, "only the map itself remains");
        fs::write(&path, b"not a map").expect("clobber");
        let err = read(&path).expect_err("garbage");
        assert!(err.to_string().contains("scene.geoloc"), "{err}");
        let err = read(&dir.join("nope.geoloc")).expect_err("missing file");
        assert!(matches!(err, GeolocError::Io { .. }), "{err:?}");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn a_header_length_beyond_the_file_is_named_before_parsing() {
        let mut bytes = sample().to_bytes().expect("serializes");
        bytes[..8].copy_from_slice(&(1u64 << 40).to_le_bytes());
        let err = MapFile::from_bytes(&bytes).expect_err("claims a terabyte of header");
        assert!(err.to_string().contains("header length field claims 1099511627776 bytes"), "{err}");
    }

    #[test]
    fn read_checks_the_header_before_the_arrays() {
        let dir = std::env::temp_dir().join(format!("geoloc-mapfile-extent-{}", std::process::id()));
        fs::create_dir_all(&dir).expect("temp dir");
        let bytes = sample().to_bytes().expect("serializes");
        let path = dir.join("m.geoloc");
        fs::write(&path, &bytes).expect("writes");
        assert_eq!(read(&path).expect("a whole map reads"), sample());
        // the arrays' extent, by the safetensors crate (an independent reader): 8 + header + data
        let (header_len, _) = SafeTensors::read_metadata(&bytes).expect("valid");
        assert_eq!(check_array_extent(&bytes[8..8 + header_len], bytes.len() as u64).ok(), Some(()));
        let mut longer = bytes.clone();
        longer.extend_from_slice(&[0; 3]);
        fs::write(&path, &longer).expect("writes");
        let n = bytes.len();
        let err = read(&path).expect_err("bytes appended");
        assert!(err.to_string().contains(&format!("describes {n} bytes but the file holds {}", n + 3)), "{err}");
        fs::write(&path, &bytes[..n - 1]).expect("writes");
        let err = read(&path).expect_err("cut in the arrays");
        assert!(err.to_string().contains(&format!("describes {n} bytes but the file holds {}", n - 1)), "{err}");
        // zeros: an empty header, refused from the first 8 bytes
        fs::write(&path, vec![0u8; 4096]).expect("writes");
        let err = read(&path).expect_err("zeros");
        assert!(err.to_string().contains("invalid JSON header"), "{err}");
        fs::remove_dir_all(&dir).expect("cleans up");
    }

    #[test]
    fn a_header_length_beyond_the_limit_is_refused_unread() {
        assert!(check_header_length(MAX_HEADER_BYTES, MAX_HEADER_BYTES + 8).is_ok());
        let err = check_header_length(MAX_HEADER_BYTES + 1, u64::MAX).expect_err("over the limit");
        assert!(err.to_string().contains("more than a map's header may be"), "{err}");
        let err = check_header_length(10, 17).expect_err("9 bytes follow the field");
        assert!(err.to_string().contains("claims 10 bytes, but only 9 follow it"), "{err}");
    }

    #[test]
    fn concurrent_saves_to_one_path_leave_one_complete_map() {
        const THREADS: usize = 4;
        const ROUNDS: usize = 25;
        let dir = std::env::temp_dir().join(format!("geoloc-mapfile-concurrent-{}", std::process::id()));
        fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("scene.geoloc");
        let maps: Vec<MapFile> =
            (0..THREADS).map(|i| MapFile { header: format!("{{\"writer\":{i}}}"), ..sample() }).collect();
        std::thread::scope(|scope| {
            for map in &maps {
                let path = &path;
                scope.spawn(move || {
                    for _ in 0..ROUNDS {
                        write(path, map).expect("every concurrent save succeeds");
                    }
                });
            }
        });
        let back = read(&path).expect("the map loads");
        assert!(maps.contains(&back), "one writer's map, complete");
        let names: Vec<_> = fs::read_dir(&dir).expect("list").filter_map(|e| e.ok()).collect();
        assert_eq!(names.len(), 1, "no temp files remain");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn a_fifo_is_refused_without_blocking() {
        let dir = std::env::temp_dir().join(format!("geoloc-mapfile-fifo-{}", std::process::id()));
        fs::create_dir_all(&dir).expect("temp dir");
        let fifo = dir.join("scene.geoloc");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status().is_ok_and(|s| s.success());
        if made {
            // reading would block forever (no writer); the check refuses it before opening
            let err = read(&fifo).expect_err("a FIFO is not a map");
            assert!(matches!(err, GeolocError::Io { .. }), "{err:?}");
            assert!(err.to_string().contains("scene.geoloc: not a regular file (a FIFO)"), "{err}");
        }
        let err = read(&dir).expect_err("a folder is not a map");
        assert!(err.to_string().contains("not a regular file (a folder)"), "{err}");
        fs::remove_dir_all(&dir).expect("cleanup");
    }
}
