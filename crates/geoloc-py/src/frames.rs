//! Bindings of `geoloc_core::frames`: the frame-stream writer behind `geoloc.export_frames`,
//! so Python and `geoloc-rs` share one implementation of the format.
//!
//! The stream goes to a temp file of its own beside `path` (core's
//! [`geoloc_core::files::AtomicFile`]: `.NAME.PID.N.tmp`, created exclusively) and is renamed
//! onto `path` by `close()` after an fsync: an interrupted export never leaves a half-written
//! stream at `path`, nor destroys a previous one, and concurrent writers to one path never
//! share a temp file. `abort()` (or dropping the writer unclosed) removes the temp file.

use std::path::PathBuf;
use std::sync::Mutex;

use geoloc_core::files::AtomicFile;
use geoloc_core::frames::{FrameRecord, write_json_header, write_json_record, write_record, write_stream_header};
use numpy::{PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;

use crate::convert::{BorrowedDescriptors, rows};
use crate::errors::{invalid, to_py_err};

/// An open stream: the temp file (removed when dropped uncommitted), its encoding and how
/// many records it holds.
struct Open {
    out: AtomicFile,
    json: bool,
    frames: usize,
}

/// Writes a frame stream atomically; see the module doc.
#[pyclass(module = "geoloc._core", frozen)]
pub struct FrameWriter {
    state: Mutex<Option<Open>>,
}

impl FrameWriter {
    fn with_open<R>(&self, f: impl FnOnce(&mut Open) -> PyResult<R>) -> PyResult<R> {
        let mut guard = self.state.lock().map_err(|_| invalid("writer", "a previous call panicked"))?;
        f(guard.as_mut().ok_or_else(|| invalid("writer", "is closed"))?)
    }
}

#[pymethods]
impl FrameWriter {
    #[new]
    #[pyo3(signature = (path, *, format="binary"))]
    fn new(path: PathBuf, format: &str) -> PyResult<Self> {
        let json = match format {
            "binary" => false,
            "jsonl" => true,
            other => return Err(invalid("format", format!("expected \"binary\" or \"jsonl\", got {other:?}"))),
        };
        if path.file_name().is_none() {
            return Err(invalid("path", "expected a file path"));
        }
        let mut out = AtomicFile::create(&path).map_err(to_py_err)?;
        let header = if json { write_json_header(&mut out) } else { write_stream_header(&mut out) };
        let open = Open { out, json, frames: 0 };
        header.map_err(to_py_err)?;
        Ok(Self { state: Mutex::new(Some(open)) })
    }

    /// Appends one frame: keypoints (N, 2) undistorted px, pixel_sigmas (N,) px, descriptors
    /// (N, W) uint8 or float32, the global descriptor (D,) float32 or None.
    #[pyo3(signature = (timestamp, keypoints, pixel_sigmas, descriptors, global_descriptor=None))]
    fn write(
        &self,
        timestamp: f64,
        keypoints: PyReadonlyArray2<'_, f64>,
        pixel_sigmas: PyReadonlyArray1<'_, f64>,
        descriptors: Bound<'_, PyAny>,
        global_descriptor: Option<PyReadonlyArray1<'_, f32>>,
    ) -> PyResult<()> {
        let xy = rows::<2>("keypoints", &keypoints)?;
        let sigmas = pixel_sigmas.as_slice().map_err(|_| invalid("pixel_sigmas", "must be contiguous"))?;
        let global = global_descriptor
            .map(|g| g.as_slice().map(<[f32]>::to_vec).map_err(|_| invalid("global_descriptor", "must be contiguous")))
            .transpose()?;
        let record = FrameRecord {
            timestamp,
            keypoints: xy.chunks_exact(2).map(|p| nalgebra::Vector2::new(p[0], p[1])).collect(),
            pixel_sigmas: sigmas.to_vec(),
            descriptors: BorrowedDescriptors::extract(&descriptors, "descriptors")?.to_owned_set("descriptors")?,
            global,
        };
        self.with_open(|o| {
            let written = if o.json {
                write_json_record(&mut o.out, &record, o.frames)
            } else {
                write_record(&mut o.out, &record, o.frames)
            };
            written.map_err(to_py_err)?;
            o.frames += 1;
            Ok(())
        })
    }

    /// Number of frames written so far.
    #[getter]
    fn frames_written(&self) -> PyResult<usize> {
        self.with_open(|o| Ok(o.frames))
    }

    /// Flushes, syncs and renames the stream onto its path; returns the number of frames.
    fn close(&self) -> PyResult<usize> {
        let mut guard = self.state.lock().map_err(|_| invalid("writer", "a previous call panicked"))?;
        let o = guard.take().ok_or_else(|| invalid("writer", "is closed"))?;
        o.out.commit().map_err(to_py_err)?;
        Ok(o.frames)
    }

    /// Drops the stream: the temp file is removed and `path` is left as it was.
    fn abort(&self) -> PyResult<()> {
        self.state.lock().map_err(|_| invalid("writer", "a previous call panicked"))?.take();
        Ok(())
    }
}

/// Registers the class on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<FrameWriter>()
}
