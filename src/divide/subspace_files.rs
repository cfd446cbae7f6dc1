//! The files a division writes: binary little-endian PLYs of point records whose header has a
//! fixed length (a padding comment absorbs the digits of the vertex count), so points are
//! appended as they stream in and the count is written in place at the end; each file is a
//! standard PLY that any reader opens.

use std::fs::{File, OpenOptions};
use std::path::PathBuf;

use super::PointLayout;

/// Digits of the largest vertex count.
const COUNT_DIGITS: usize = 20;

/// The header of a file of `count` records of `layout`, always of the same length for one
/// layout and note.
pub fn fixed_header(layout: &PointLayout, count: u64, note: &str) -> Vec<u8> {
    let digits = count.to_string().len();
    let padding = " ".repeat(COUNT_DIGITS.saturating_sub(digits));
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment octstore divide: {note}\nelement vertex {count}\n{}comment{padding}\nend_header\n",
        layout.ply_properties()
    )
    .into_bytes()
}

/// Output files filled by appends in the order of the calls: each file's bytes (its header
/// first) wait in memory until they pass their share of `buffer_limit`, then go to the file.
/// Buffers keep their capacity between writes (no page faults on every refill), so with those
/// on their way to the file they take at most twice the limit.
///
/// The whole pages of a buffer are written with `O_DIRECT` where the file system takes it:
/// through the page cache, the kernel's copy and writeback cost about a second of CPU per GB
/// on a 2-core machine, a quarter of the write pass. The partial page left at
/// the end, and every write on a file system that refuses direct I/O, go through the page
/// cache; the bytes in the files are the same either way. The pages are written on threads
/// of their own ([`Writer`]), so a pass's workers go on while the disk takes them.
pub struct Appenders {
    layout: PointLayout,
    paths: Vec<PathBuf>,
    notes: Vec<String>,
    buffers: Vec<PageBuffer>,
    records: Vec<u64>,
    /// Bytes of each file handed to the writer so far: whole pages.
    written: Vec<u64>,
    share: usize,
    writer: Writer,
}

/// Whole pages of a file on their way to it: the first `whole` bytes of `buffer`, at `offset`.
struct PagesJob {
    path: PathBuf,
    offset: u64,
    buffer: PageBuffer,
    whole: usize,
}

/// The threads that write [`PagesJob`]s, and the buffers they are done with. Jobs wait in a
/// queue of [`WRITES_IN_FLIGHT`], which bounds the memory they hold.
///
/// Several threads, because a direct write returns only when the disk has the pages: one
/// thread writing a file's share at a time left the pass's workers waiting for the queue
/// ([`WRITER_THREADS`] has the figures). Jobs of one file may be written in any order:
/// each names its offset, and every file exists before the first job is queued.
struct Writer {
    jobs: Option<std::sync::mpsc::SyncSender<PagesJob>>,
    spares: std::sync::mpsc::Receiver<PageBuffer>,
    threads: Vec<std::thread::JoinHandle<std::io::Result<()>>>,
}

/// Jobs queued for the writers besides those being written.
const WRITES_IN_FLIGHT: usize = 8;

/// Threads writing pages at once. Measured on a 2-core machine, 10^9 generated
/// points at 256 MiB, alternating, the write pass: one thread (and the release before's
/// locator), 54.0 and 49.2 s; four, 43.3 and 47.4 s (both with buffers of an eighth of the
/// budget); with today's buffers, four, 36.6 and 38.4 s; eight, 33.0 and 33.6 s. The threads
/// wait on the disk, not on the CPU.
const WRITER_THREADS: usize = 8;

impl Writer {
    /// Writers whose first writes try `O_DIRECT` when `direct`.
    fn start(direct: bool) -> std::io::Result<Writer> {
        use std::os::unix::fs::FileExt;
        use std::sync::atomic::{AtomicBool, Ordering};
        let (jobs, queue) = std::sync::mpsc::sync_channel::<PagesJob>(WRITES_IN_FLIGHT);
        let queue = std::sync::Arc::new(std::sync::Mutex::new(queue));
        // Set by a writer that failed, so that the others stop and the queue refuses jobs.
        let failed = std::sync::Arc::new(AtomicBool::new(false));
        let (done, spares) = std::sync::mpsc::channel();
        let mut threads = Vec::with_capacity(WRITER_THREADS);
        for _ in 0..WRITER_THREADS {
            let (queue, failed, done) = (queue.clone(), failed.clone(), done.clone());
            let mut direct = direct;
            let mut write = move |job: &PagesJob| -> std::io::Result<()> {
                let pages = job.buffer.bytes().get(..job.whole).unwrap_or_default();
                if direct {
                    match open_for_writes(&job.path, false, true).and_then(|f| f.write_all_at(pages, job.offset)) {
                        Ok(()) => return Ok(()),
                        Err(e) if refuses_direct(&e) => direct = false,
                        Err(e) => return Err(e),
                    }
                }
                open_for_writes(&job.path, false, false)?.write_all_at(pages, job.offset)
            };
            let thread =
                std::thread::Builder::new()
                    .name("divide-writer".into())
                    .spawn(move || -> std::io::Result<()> {
                        loop {
                            // The lock is held only to take a job; a poisoned lock means another
                            // writer panicked, which `stop` reports.
                            let next = match queue.lock() {
                                Ok(queue) => queue.recv(),
                                Err(_) => return Ok(()),
                            };
                            let Ok(mut job) = next else { return Ok(()) };
                            if failed.load(Ordering::Relaxed) {
                                return Ok(());
                            }
                            if let Err(e) = write(&job) {
                                failed.store(true, Ordering::Relaxed);
                                return Err(e);
                            }
                            job.buffer.filled = 0;
                            // The appenders may be gone: then the buffer is not needed.
                            let _ = done.send(job.buffer);
                        }
                    })?;
            threads.push(thread);
        }
        Ok(Writer {
            jobs: Some(jobs),
            spares,
            threads,
        })
    }

    /// Queues `job`; an error when a writer has failed (its error) or they are gone.
    fn send(&mut self, job: PagesJob) -> std::io::Result<()> {
        match self.jobs.as_ref().map(|jobs| jobs.send(job)) {
            Some(Ok(())) => Ok(()),
            _ => Err(self
                .stop()
                .err()
                .unwrap_or_else(|| std::io::Error::other("the file writer stopped"))),
        }
    }

    /// Waits for every queued job to be written; the first writer's error if one failed.
    fn stop(&mut self) -> std::io::Result<()> {
        self.jobs = None;
        let mut outcome = Ok(());
        for thread in self.threads.drain(..) {
            let result = match thread.join() {
                Ok(result) => result,
                Err(_) => Err(std::io::Error::other("the file writer panicked")),
            };
            if outcome.is_ok() {
                outcome = result;
            }
        }
        outcome
    }
}

impl Drop for Writer {
    /// No file is written after the appenders are dropped (a failed pass removes its files).
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

/// The least a buffer holds before it is written: smaller writes cost more in system calls
/// than they save in memory.
const MIN_SHARE: usize = 64 << 10;

/// The alignment of direct I/O's memory, file offsets and lengths: a page, which every file
/// system's logical block divides.
const PAGE: usize = 4096;

/// A page of memory, aligned as direct I/O needs.
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(4096))]
struct Page([u8; PAGE]);

/// A file's bytes waiting to be written, in page-aligned memory.
#[derive(Default)]
struct PageBuffer {
    pages: Vec<Page>,
    filled: usize,
}

impl PageBuffer {
    fn bytes(&self) -> &[u8] {
        bytemuck::cast_slice::<Page, u8>(&self.pages)
            .get(..self.filled)
            .unwrap_or_default()
    }

    fn extend(&mut self, bytes: &[u8]) {
        let end = self.filled + bytes.len();
        if end > self.pages.len() * PAGE {
            self.pages.resize(end.div_ceil(PAGE), Page([0; PAGE]));
        }
        if let Some(to) = bytemuck::cast_slice_mut::<Page, u8>(&mut self.pages).get_mut(self.filled..end) {
            to.copy_from_slice(bytes);
        }
        self.filled = end;
    }
}

/// Opens `path` for writing at any offset: created empty when `create`, with `O_DIRECT` when
/// `direct`.
fn open_for_writes(path: &std::path::Path, create: bool, direct: bool) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut options = OpenOptions::new();
    options.write(true).create(create).truncate(create);
    if direct {
        options.custom_flags(libc::O_DIRECT);
    }
    options.open(path)
}

/// Whether an error says the file system does not take direct I/O (tmpfs refuses the open,
/// some file systems the write).
fn refuses_direct(error: &std::io::Error) -> bool {
    error.raw_os_error() == Some(libc::EINVAL)
}

impl Appenders {
    /// One appender per path, each with the note its header carries.
    pub fn new(layout: PointLayout, files: Vec<(PathBuf, String)>, buffer_limit: usize) -> std::io::Result<Appenders> {
        Appenders::with_direct_io(layout, files, buffer_limit, true)
    }

    /// [`Appenders::new`], trying direct I/O only when `direct`.
    fn with_direct_io(
        layout: PointLayout,
        files: Vec<(PathBuf, String)>,
        buffer_limit: usize,
        direct: bool,
    ) -> std::io::Result<Appenders> {
        let n = files.len();
        let (paths, notes): (Vec<PathBuf>, Vec<String>) = files.into_iter().unzip();
        // Every file exists, empty, before a job is queued (the writers only open them).
        for path in &paths {
            open_for_writes(path, true, false)?;
        }
        let buffers = notes
            .iter()
            .map(|note| {
                let mut buffer = PageBuffer::default();
                buffer.extend(&fixed_header(&layout, 0, note));
                buffer
            })
            .collect();
        Ok(Appenders {
            layout,
            paths,
            notes,
            buffers,
            records: vec![0; n],
            written: vec![0; n],
            // Besides the files' own buffers, at most `WRITES_IN_FLIGHT + WRITER_THREADS + 1`
            // exist: queued, being written, and the one waiting for room in the queue (a
            // buffer handed back is reused before a new one is made).
            share: (buffer_limit / (n + WRITES_IN_FLIGHT + WRITER_THREADS + 1)).max(MIN_SHARE),
            writer: Writer::start(direct)?,
        })
    }

    /// Appends whole records to file `target`.
    pub fn append(&mut self, target: usize, records: &[u8]) -> std::io::Result<()> {
        let Some(buffer) = self.buffers.get_mut(target) else {
            return Err(std::io::Error::other(format!("no output file {target}")));
        };
        buffer.extend(records);
        let full = buffer.filled >= self.share;
        if let Some(r) = self.records.get_mut(target) {
            *r += (records.len() / self.layout.record_len().max(1)) as u64;
        }
        if full {
            self.write_pages(target)?;
        }
        Ok(())
    }

    /// Hands file `target`'s whole pages to the writer, keeping the partial page that ends
    /// them.
    fn write_pages(&mut self, target: usize) -> std::io::Result<()> {
        let (Some(buffer), Some(path), Some(written)) = (
            self.buffers.get_mut(target),
            self.paths.get(target),
            self.written.get_mut(target),
        ) else {
            return Ok(());
        };
        let whole = buffer.filled / PAGE * PAGE;
        if whole == 0 {
            return Ok(());
        }
        let mut next = self.writer.spares.try_recv().unwrap_or_default();
        next.extend(buffer.bytes().get(whole..).unwrap_or_default());
        let job = PagesJob {
            path: path.clone(),
            offset: *written,
            buffer: std::mem::replace(buffer, next),
            whole,
        };
        *written += whole as u64;
        self.writer.send(job)
    }

    /// Writes what waits, sets each file's vertex count, syncs them, and returns the counts.
    /// A file that received no record is created with an empty body.
    pub fn finish(mut self) -> std::io::Result<Vec<u64>> {
        use std::os::unix::fs::FileExt;
        self.writer.stop()?;
        for (((path, note), (records, written)), buffer) in self
            .paths
            .iter()
            .zip(&self.notes)
            .zip(self.records.iter().zip(&self.written))
            .zip(&self.buffers)
        {
            let file = open_for_writes(path, *written == 0, false)?;
            file.write_all_at(buffer.bytes(), *written)?;
            file.write_all_at(&fixed_header(&self.layout, *records, note), 0)?;
            file.sync_all()?;
        }
        Ok(self.records)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::divide::open_point_cloud;
    use crate::format::ply_header::PlyScalar;

    #[test]
    fn appended_files_are_plys_with_their_count() -> Result<(), Box<dyn std::error::Error>> {
        let layout = PointLayout::new(vec![
            ("x".into(), PlyScalar::F32),
            ("y".into(), PlyScalar::F32),
            ("z".into(), PlyScalar::F32),
            ("red".into(), PlyScalar::U8),
        ])?;
        assert_eq!(
            fixed_header(&layout, 0, "n").len(),
            fixed_header(&layout, u64::MAX, "n").len()
        );
        let dir = tempfile::tempdir()?;
        let files = vec![
            (dir.path().join("a.ply"), "a".to_string()),
            (dir.path().join("b.ply"), "b".to_string()),
        ];
        let mut appenders = Appenders::new(layout.clone(), files, 20)?;
        let record = |x: f32| {
            let mut r = Vec::new();
            for v in [x, 1.0, 2.0] {
                r.extend(v.to_le_bytes());
            }
            r.push(7);
            r
        };
        for i in 0..10 {
            appenders.append(i % 2, &record(i as f32))?;
        }
        assert_eq!(appenders.finish()?, vec![5, 5]);
        let file = open_point_cloud(&dir.path().join("b.ply"))?;
        assert_eq!(file.announced_points(), Some(5));
        assert_eq!(file.layout(), &layout);
        let mut xs = Vec::new();
        file.for_each_block::<crate::inputs::InputError>(3, |block| {
            xs.extend(block.chunks_exact(13).map(|r| layout.position(r)[0]));
            Ok(())
        })?;
        assert_eq!(xs, vec![1.0, 3.0, 5.0, 7.0, 9.0]);
        Ok(())
    }

    /// Files of many pages, written directly and through the page cache, hold the header and
    /// the records in order, whatever page boundaries the appends cross.
    #[test]
    fn files_of_many_pages_hold_their_records_in_order() -> Result<(), Box<dyn std::error::Error>> {
        let layout = PointLayout::new(["x", "y", "z"].map(|n| (n.to_string(), PlyScalar::F32)).into())?;
        for direct in [true, false] {
            let dir = tempfile::tempdir()?;
            let files: Vec<(PathBuf, String)> = (0..3)
                .map(|i| (dir.path().join(format!("{i}.ply")), format!("file {i}")))
                .collect();
            let mut appenders = Appenders::with_direct_io(layout.clone(), files.clone(), 0, direct)?;
            let mut expected = vec![Vec::new(); 3];
            // Appends of 1 to 997 records (12 bytes each) pass the 64 KiB share many times.
            for i in 0u32..600 {
                let target = (i % 3) as usize;
                let records: Vec<u8> = (0..(i * 7919 % 997 + 1))
                    .flat_map(|r| [i as f32, r as f32, 0.5].map(f32::to_le_bytes))
                    .flatten()
                    .collect();
                appenders.append(target, &records)?;
                if let Some(e) = expected.get_mut(target) {
                    e.extend_from_slice(&records);
                }
            }
            // File 2 also receives nothing more; a fourth would receive nothing at all.
            let counts = appenders.finish()?;
            for (((path, note), records), count) in files.iter().zip(&expected).zip(&counts) {
                assert_eq!(*count, (records.len() / 12) as u64);
                let mut whole = fixed_header(&layout, *count, note);
                whole.extend_from_slice(records);
                assert!(std::fs::read(path)? == whole, "{path:?}, direct {direct}");
            }
        }
        Ok(())
    }
}
