//! How geoloc touches files: atomic replacement for every writer, the regular-file check
//! before every read, and whether two paths name one file.
//!
//! * **Atomic replacement** ([`AtomicFile`], [`write_atomic`]): the content goes to a temp
//!   file `.NAME.PID.N.tmp` beside the target, created with `O_CREAT | O_EXCL` (so no two
//!   writers ever share one; `N` is a process-wide counter), then `fsync`, `rename` over the
//!   target, and `fsync` of the folder. A reader of the target sees the previous file or the
//!   new one, complete, never a mixture; of concurrent writers to one path the last rename
//!   wins. On any failure, or when the writer is dropped uncommitted, the temp file is
//!   removed and the target is left as it was. `NAME` is the target's name cut to
//!   [`TEMP_STEM_BYTES`] (a target name of the file system's full length still gets a temp
//!   name that fits). The new file keeps the permissions of the one it replaces; a new
//!   target gets the permissions a plain create gives (0666 less the umask). A target that is
//!   a symlink is written through: the file it points to is replaced and the link kept (a
//!   dangling link is refused, as `cp` refuses it).
//! * **Regular files only** ([`check_regular_file`], [`open_regular`]): opening a FIFO for
//!   reading blocks until a writer appears, and a device can stream forever, so readers
//!   refuse anything but a regular file (symlinks are followed) before opening it.
//! * **Aliasing** ([`same_file`]): an output that is one of the inputs (the same path, another
//!   spelling, a symlink or a hard link) would destroy that input, so writers compare them
//!   first.
//!
//! ```
//! use geoloc_core::files::{same_file, write_atomic};
//! let dir = std::env::temp_dir().join(format!("geoloc-files-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).expect("temp dir");
//! let path = dir.join("a.txt");
//! write_atomic(&path, b"hello").expect("writes");
//! assert_eq!(std::fs::read(&path).expect("reads"), b"hello");
//! assert!(same_file(&path, &dir.join(".").join("a.txt")));
//! assert!(!same_file(&path, &dir.join("missing.txt")));
//! std::fs::remove_dir_all(&dir).expect("cleanup");
//! ```

use std::fs::{self, File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::error::{GeolocError, Result};

/// Temp names tried before [`AtomicFile::create`] gives up (only leftovers of an earlier
/// process with the same id can be in the way).
const TEMP_ATTEMPTS: u32 = 1000;

/// The process-wide counter that makes each temp name unique within this process.
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// The longest part of the target's name a temp name repeats (bytes): `.NAME.PID.N.tmp` must
/// fit the 255 bytes a file name may have wherever the target's name fits.
pub const TEMP_STEM_BYTES: usize = 64;

/// The first `TEMP_STEM_BYTES` bytes of `name`, cut at a character boundary.
fn temp_stem(name: &str) -> &str {
    let mut end = name.len().min(TEMP_STEM_BYTES);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    &name[..end]
}

/// The file a write to `path` replaces: `path` itself, or the file a symlink at `path`
/// points to (followed to the end).
///
/// # Errors
/// `Io` naming `path` when it is a symlink to nothing.
fn written_through(path: &Path) -> Result<PathBuf> {
    match fs::symlink_metadata(path) {
        Ok(meta) if meta.file_type().is_symlink() => fs::canonicalize(path).map_err(|e| {
            io_error(path, "a symlink to a file that does not exist (not written through a dangling link)", &e)
        }),
        _ => Ok(path.to_path_buf()),
    }
}

fn io_error(path: &Path, what: &str, e: &std::io::Error) -> GeolocError {
    GeolocError::Io { path: path.display().to_string(), reason: format!("{what}: {e}") }
}

/// A file being written that replaces `path` only when [`AtomicFile::commit`] succeeds; see
/// the module doc. Writes are buffered.
#[derive(Debug)]
pub struct AtomicFile {
    /// The open temp file (None once committed).
    out: Option<BufWriter<File>>,
    tmp: PathBuf,
    path: PathBuf,
    folder: PathBuf,
}

impl AtomicFile {
    /// Creates a new, unique temp file beside `path`.
    ///
    /// # Errors
    /// `Io` naming `path` when `path` has no file name (it names a folder), when its folder
    /// does not exist or is not writable, or when `path` exists and is not a regular file (a
    /// folder, a FIFO, a device: replacing it by a regular file would be a surprise).
    pub fn create(path: &Path) -> Result<Self> {
        let path = &written_through(path)?;
        let folder = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = path.file_name().ok_or_else(|| GeolocError::Io {
            path: path.display().to_string(),
            reason: "expected a file path, not a folder".into(),
        })?;
        if !folder.is_dir() {
            return Err(io_error(path, "folder does not exist", &std::io::Error::from(std::io::ErrorKind::NotFound)));
        }
        let replaced = fs::metadata(path).ok();
        if let Some(meta) = &replaced
            && !meta.is_file()
        {
            // renaming over /dev/null or a FIFO would replace it with a regular file
            return Err(GeolocError::Io {
                path: path.display().to_string(),
                reason: format!("not a regular file ({}); refusing to replace it", kind_of(meta.file_type())),
            });
        }
        let name = name.to_string_lossy();
        let name = temp_stem(&name);
        let pid = std::process::id();
        for _ in 0..TEMP_ATTEMPTS {
            let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
            let tmp = folder.join(format!(".{name}.{pid}.{n}.tmp"));
            match OpenOptions::new().write(true).create_new(true).open(&tmp) {
                Ok(file) => {
                    // the replaced file's permissions (a new one keeps the create's)
                    if let Some(meta) = &replaced
                        && let Err(e) = file.set_permissions(meta.permissions())
                    {
                        drop(file);
                        let _ = fs::remove_file(&tmp);
                        return Err(io_error(path, "cannot give the new file the old one's permissions", &e));
                    }
                    return Ok(Self { out: Some(BufWriter::new(file)), tmp, path: path.to_path_buf(), folder });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(io_error(path, "cannot create a temp file beside it", &e)),
            }
        }
        Err(GeolocError::Io {
            path: path.display().to_string(),
            reason: format!("{TEMP_ATTEMPTS} temp names beside it are taken"),
        })
    }

    /// The path this file replaces on commit.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes, syncs, renames the temp file over the target and syncs the folder.
    ///
    /// # Errors
    /// `Io` naming the target when any step fails; the temp file is then removed and the
    /// target is left as it was (unless only the final folder sync failed).
    pub fn commit(mut self) -> Result<()> {
        let Some(out) = self.out.take() else { return Ok(()) };
        let result = (|| -> std::io::Result<()> {
            let file = out.into_inner().map_err(std::io::IntoInnerError::into_error)?;
            file.sync_all()?;
            drop(file);
            fs::rename(&self.tmp, &self.path)?;
            File::open(&self.folder)?.sync_all()
        })();
        result.map_err(|e| {
            let _ = fs::remove_file(&self.tmp); // gone already when the rename succeeded
            io_error(&self.path, "cannot write the file", &e)
        })
    }

    fn out(&mut self) -> std::io::Result<&mut BufWriter<File>> {
        self.out.as_mut().ok_or_else(|| std::io::Error::other("the file is already committed"))
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.out()?.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.out()?.write_all(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.out()?.flush()
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if self.out.take().is_some() {
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

/// Replaces the file at `path` by `bytes` atomically (see the module doc).
///
/// # Errors
/// As [`AtomicFile::create`] and [`AtomicFile::commit`]; the target is then left as it was.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut file = AtomicFile::create(path)?;
    file.write_all(bytes).map_err(|e| io_error(path, "cannot write the file", &e))?;
    file.commit()
}

/// What a path that is not a regular file is, for error messages.
fn kind_of(file_type: fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if file_type.is_fifo() {
            return "a FIFO";
        }
        if file_type.is_socket() {
            return "a socket";
        }
        if file_type.is_block_device() || file_type.is_char_device() {
            return "a device";
        }
    }
    if file_type.is_dir() { "a folder" } else { "a FIFO, socket or device" }
}

/// The metadata of `path` (symlinks followed, the file is not opened), checked to be a
/// regular file; `what` names the file in the errors ("cannot read the map: …").
///
/// # Errors
/// `Io` naming `path` when it is missing or unreadable, or is not a regular file ("not a
/// regular file (a FIFO)", a socket, a device or a folder).
pub fn check_regular_file(path: &Path, what: &str) -> Result<fs::Metadata> {
    let meta = fs::metadata(path).map_err(|e| io_error(path, &format!("cannot read {what}"), &e))?;
    if !meta.is_file() {
        return Err(GeolocError::Io {
            path: path.display().to_string(),
            reason: format!("not a regular file ({})", kind_of(meta.file_type())),
        });
    }
    Ok(meta)
}

/// Opens `path` for reading after [`check_regular_file`], and checks the opened file again
/// (so a path swapped for a device in between is refused too). Returns the file and its
/// length in bytes.
///
/// # Errors
/// As [`check_regular_file`]; `Io` naming `path` when opening fails.
pub fn open_regular(path: &Path, what: &str) -> Result<(File, u64)> {
    check_regular_file(path, what)?;
    open_checked(path, what)
}

/// Opens `path` for reading without blocking (O_NONBLOCK on Unix: a FIFO put at `path` after
/// the check opens at once instead of waiting for a writer; it has no effect on a regular
/// file's reads) and checks that the opened file is a regular file.
fn open_checked(path: &Path, what: &str) -> Result<(File, u64)> {
    let mut options = fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path).map_err(|e| io_error(path, &format!("cannot open {what}"), &e))?;
    let meta = file.metadata().map_err(|e| io_error(path, &format!("cannot read {what}"), &e))?;
    if !meta.is_file() {
        return Err(GeolocError::Io {
            path: path.display().to_string(),
            reason: format!("not a regular file ({})", kind_of(meta.file_type())),
        });
    }
    Ok((file, meta.len()))
}

/// Whether `a` and `b` name the same existing file: the same device and inode (so hard links
/// and symlinks count), or the same canonical path. A path that does not exist is never the
/// same as another.
pub fn same_file(a: &Path, b: &Path) -> bool {
    let (Ok(meta_a), Ok(meta_b)) = (fs::metadata(a), fs::metadata(b)) else { return false };
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if meta_a.dev() == meta_b.dev() && meta_a.ino() == meta_b.ino() {
            return true;
        }
    }
    #[cfg(not(unix))]
    let _ = (meta_a, meta_b);
    matches!((fs::canonicalize(a), fs::canonicalize(b)), (Ok(x), Ok(y)) if x == y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Command;
    use std::sync::{Arc, Barrier};

    /// Threads that save to one path at once.
    const WRITERS: usize = 8;
    /// Saves per thread.
    const ROUNDS: usize = 60;
    /// Size of each writer's content (large enough that writes interleave).
    const CONTENT_BYTES: usize = 64 * 1024;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("geoloc-files-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).expect("temp dir");
        dir
    }

    fn listing(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .expect("lists")
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn concurrent_writers_to_one_path_all_succeed_and_leave_one_complete_content() {
        let dir = temp_dir("concurrent");
        let path = dir.join("map.geoloc");
        // every writer's content is distinct and self-identifying: byte i is (writer + i) mod 251
        let contents: Vec<Vec<u8>> =
            (0..WRITERS).map(|w| (0..CONTENT_BYTES).map(|i| ((w + i) % 251) as u8).collect()).collect();
        let contents = Arc::new(contents);
        let barrier = Arc::new(Barrier::new(WRITERS));
        let writing = Arc::new(std::sync::atomic::AtomicBool::new(true));
        // a reader all along: whenever the target exists, it is one writer's complete content
        let reader = {
            let (path, contents, writing) = (path.clone(), Arc::clone(&contents), Arc::clone(&writing));
            std::thread::spawn(move || {
                let mut bad_reads = 0usize;
                while writing.load(Ordering::Relaxed) {
                    if let Ok(got) = fs::read(&path)
                        && !contents.contains(&got)
                    {
                        bad_reads += 1;
                    }
                }
                bad_reads
            })
        };
        let handles: Vec<_> = (0..WRITERS)
            .map(|w| {
                let (path, contents, barrier) = (path.clone(), Arc::clone(&contents), Arc::clone(&barrier));
                std::thread::spawn(move || {
                    let mut failures = Vec::new();
                    for round in 0..ROUNDS {
                        barrier.wait();
                        if let Err(e) = write_atomic(&path, &contents[w]) {
                            failures.push(format!("writer {w} round {round}: {e}"));
                        }
                    }
                    failures
                })
            })
            .collect();
        let failures: Vec<String> = handles.into_iter().flat_map(|h| h.join().expect("no panic")).collect();
        writing.store(false, Ordering::Relaxed);
        assert!(failures.is_empty(), "{failures:?}");
        assert_eq!(reader.join().expect("no panic"), 0, "a reader saw a partial or mixed file");
        let got = fs::read(&path).expect("the target exists");
        assert!(contents.contains(&got), "the target is not one writer's complete content");
        assert_eq!(listing(&dir), ["map.geoloc"], "no temp files remain");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn a_failed_or_dropped_write_leaves_the_target_and_no_temp() {
        let dir = temp_dir("failed");
        let path = dir.join("out.txt");
        write_atomic(&path, b"old").expect("writes");
        let mut dropped = AtomicFile::create(&path).expect("creates");
        dropped.write_all(b"half of a new file").expect("writes");
        drop(dropped);
        assert_eq!(fs::read(&path).expect("reads"), b"old");
        // a folder where the target should be: refused, the folder kept
        let folder_target = dir.join("sub");
        fs::create_dir(&folder_target).expect("folder");
        fs::write(folder_target.join("keep"), b"x").expect("writes");
        let err = write_atomic(&folder_target, b"new").expect_err("cannot replace a folder");
        assert!(matches!(err, GeolocError::Io { ref path, .. } if path.ends_with("sub")), "{err:?}");
        assert!(err.to_string().contains("not a regular file (a folder)"), "{err}");
        #[cfg(unix)]
        {
            let err = AtomicFile::create(Path::new("/dev/null")).expect_err("a device is never replaced");
            assert!(err.to_string().contains("not a regular file (a device)"), "{err}");
        }
        let err = write_atomic(&dir.join("missing").join("x.txt"), b"new").expect_err("no folder");
        assert!(err.to_string().contains("missing") && err.to_string().contains("folder does not exist"), "{err}");
        assert_eq!(listing(&dir), ["out.txt", "sub"], "no temp files remain");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn a_stale_temp_name_is_skipped_not_shared() {
        let dir = temp_dir("stale");
        let path = dir.join("f.bin");
        let next = TEMP_COUNTER.load(Ordering::Relaxed);
        // leftovers of an earlier process with this id, for the next few counter values
        for n in next..next + 4 {
            fs::write(dir.join(format!(".f.bin.{}.{n}.tmp", std::process::id())), b"stale").expect("writes");
        }
        write_atomic(&path, b"fresh").expect("writes around the stale names");
        assert_eq!(fs::read(&path).expect("reads"), b"fresh");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn a_target_name_of_full_length_gets_a_temp_name_that_fits() {
        let dir = temp_dir("long");
        for name in ["a".repeat(255), format!("{}.geoloc", "é".repeat(124))] {
            let path = dir.join(&name);
            write_atomic(&path, b"long").expect("a 255-byte name is legal");
            assert_eq!(fs::read(&path).expect("reads"), b"long");
        }
        assert_eq!(listing(&dir).len(), 2, "no temp files remain");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[cfg(unix)]
    #[test]
    fn a_replaced_file_keeps_its_permissions_and_a_new_one_gets_a_plain_creates() {
        use std::os::unix::fs::PermissionsExt;
        let dir = temp_dir("mode");
        let mode = |p: &Path| fs::metadata(p).expect("exists").permissions().mode() & 0o7777;
        let kept = dir.join("kept.txt");
        fs::write(&kept, b"old").expect("writes");
        fs::set_permissions(&kept, fs::Permissions::from_mode(0o640)).expect("chmod");
        write_atomic(&kept, b"new").expect("writes");
        assert_eq!((fs::read(&kept).expect("reads"), mode(&kept)), (b"new".to_vec(), 0o640));
        // a new target: what std's plain create gives in the same folder (0666 less the umask)
        let plain = dir.join("plain.txt");
        fs::write(&plain, b"x").expect("writes");
        let fresh = dir.join("fresh.txt");
        write_atomic(&fresh, b"x").expect("writes");
        assert_eq!(mode(&fresh), mode(&plain));
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[cfg(unix)]
    #[test]
    fn a_symlinked_target_is_written_through_and_a_dangling_one_refused() {
        let dir = temp_dir("link");
        let real = dir.join("real.txt");
        fs::write(&real, b"old").expect("writes");
        let link = dir.join("link.txt");
        std::os::unix::fs::symlink("real.txt", &link).expect("symlink");
        write_atomic(&link, b"new").expect("writes through the link");
        assert!(fs::symlink_metadata(&link).expect("exists").file_type().is_symlink(), "the link is kept");
        assert_eq!(fs::read(&real).expect("reads"), b"new");
        let dangling = dir.join("dangling.txt");
        std::os::unix::fs::symlink("nowhere.txt", &dangling).expect("symlink");
        let err = write_atomic(&dangling, b"new").expect_err("refused");
        assert!(err.to_string().contains("dangling") && err.to_string().contains("dangling.txt"), "{err}");
        assert_eq!(listing(&dir), ["dangling.txt", "link.txt", "real.txt"], "nothing else written");
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn same_file_sees_aliases_and_never_a_missing_path() {
        let dir = temp_dir("same");
        let a = dir.join("a.bin");
        fs::write(&a, b"input").expect("writes");
        let b = dir.join("b.bin");
        fs::write(&b, b"input").expect("writes"); // same content, another file
        let hard = dir.join("hard.bin");
        fs::hard_link(&a, &hard).expect("hard link");
        #[cfg(unix)]
        std::os::unix::fs::symlink(&a, dir.join("sym.bin")).expect("symlink");
        assert!(same_file(&a, &a));
        assert!(same_file(&a, &dir.join(".").join("a.bin")));
        assert!(same_file(&a, &dir.join("..").join(dir.file_name().expect("name")).join("a.bin")));
        assert!(same_file(&a, &hard));
        #[cfg(unix)]
        assert!(same_file(&dir.join("sym.bin"), &a));
        assert!(!same_file(&a, &b));
        assert!(!same_file(&a, &dir.join("missing.bin")));
        assert!(!same_file(&dir.join("missing.bin"), &dir.join("missing.bin")));
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn special_files_are_refused_before_opening() {
        let dir = temp_dir("special");
        let fifo = dir.join("pipe");
        let made = Command::new("mkfifo").arg(&fifo).status().is_ok_and(|s| s.success());
        if made {
            // opening a FIFO would block forever without a writer: the check must not open it
            let err = open_regular(&fifo, "the file").expect_err("a FIFO is refused");
            assert!(err.to_string().contains("not a regular file (a FIFO)"), "{err}");
            assert!(err.to_string().contains("pipe"), "{err}");
        }
        let err = check_regular_file(&dir, "the file").expect_err("a folder is refused");
        assert!(err.to_string().contains("not a regular file (a folder)"), "{err}");
        #[cfg(unix)]
        {
            let err = check_regular_file(Path::new("/dev/null"), "the file").expect_err("a device is refused");
            assert!(err.to_string().contains("not a regular file (a device)"), "{err}");
        }
        let file = dir.join("plain");
        fs::write(&file, b"12345").expect("writes");
        assert_eq!(open_regular(&file, "the file").expect("a regular file opens").1, 5);
        assert_eq!(open_checked(&file, "the file").expect("opens").1, 5);
        fs::remove_dir_all(&dir).expect("cleanup");
    }

    /// A path swapped for a FIFO after the check (here: opened with no check at all) is
    /// opened without blocking and refused; a blocking open would wait for a writer forever.
    #[test]
    fn a_fifo_swapped_in_after_the_check_does_not_block() {
        let dir = temp_dir("swapped");
        let fifo = dir.join("pipe");
        if Command::new("mkfifo").arg(&fifo).status().is_ok_and(|s| s.success()) {
            let (sender, receiver) = std::sync::mpsc::channel();
            let path = fifo.clone();
            std::thread::spawn(move || {
                sender.send(open_checked(&path, "the map").map(|_| ()).map_err(|e| e.to_string()))
            });
            let result = receiver.recv_timeout(std::time::Duration::from_secs(10)).expect("the open returned");
            let err = result.expect_err("a FIFO is refused");
            assert!(err.contains("not a regular file (a FIFO)") && err.contains("pipe"), "{err}");
        }
        fs::remove_dir_all(&dir).expect("cleanup");
    }
}
