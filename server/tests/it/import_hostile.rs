//! `isovox import` of inputs made to hurt the machine that reads them: decompression bombs in
//! Zarr chunks (zstd, gzip, blosc; v2 and v3; local and over http), headers that promise more
//! voxels than their file holds (NIfTI plain and gzip, RAW with --dims, TIFF strips), metadata
//! paths that lead outside the directory or URL prefix given, and files that are not what their
//! name says.
//!
//! Each test builds its input in a temporary directory (small on disk), runs the real binary
//! as a child process and asserts that it fails with status 1 and a message naming the file or
//! chunk and what is wrong, that its peak resident memory (VmHWM, polled from `/proc`) stays
//! under [`PEAK_BOUND`], and that it ends within [`HANG_GUARD`]. The time limit is a guard
//! against an import that runs for minutes, not a measure of speed. To keep a regression from
//! taking the machine down, the child runs under an address-space limit and is killed when its
//! memory passes [`KILL_AT`].

use crate::server_process;
use server_process::isovox;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Peak resident memory an import of any of these inputs may reach: the process itself and a
/// few chunks or slabs of the (small) volumes they declare, far from what they claim to hold.
const PEAK_BOUND: u64 = 200 << 20;
/// The import is killed past this much resident memory (the test then fails on the bound).
const KILL_AT: u64 = 1536 << 20;
/// Address space the child may map: an allocation of what a bomb declares fails instead of
/// being granted.
const ADDRESS_SPACE: u64 = 3_000_000_000;
/// A hang guard: a refused input is refused in well under a second; this only tells "refused"
/// from "ran on for minutes".
const HANG_GUARD: Duration = Duration::from_secs(20);

/// What a child `isovox import` did.
#[derive(Debug)]
struct Outcome {
    /// The exit code; `None` when killed by a signal (an abort, or the guards).
    code: Option<i32>,
    stderr: String,
    /// VmHWM, bytes.
    peak: u64,
    elapsed: Duration,
    /// Why the guards killed it, if they did.
    killed: Option<String>,
}

impl Outcome {
    /// Asserts a clean refusal: status 1, every one of `needles` in the message, memory and
    /// time within the bounds.
    fn assert_refused(&self, needles: &[&str]) {
        assert!(self.killed.is_none(), "killed: {self:#?}");
        assert_eq!(self.code, Some(1), "{self:#?}");
        for needle in needles {
            assert!(
                self.stderr.contains(needle),
                "{needle:?} not in the message: {self:#?}"
            );
        }
        assert!(
            self.peak < PEAK_BOUND,
            "peak resident memory {} MiB, bound {} MiB: {self:#?}",
            self.peak >> 20,
            PEAK_BOUND >> 20
        );
        assert!(self.elapsed < HANG_GUARD, "{self:#?}");
        // Numbers in messages stay readable (f64's largest prints with 309 digits).
        let longest_number = self
            .stderr
            .split(|c: char| !c.is_ascii_digit())
            .map(str::len)
            .max()
            .unwrap_or(0);
        assert!(
            longest_number <= 24,
            "a {longest_number}-digit number: {self:#?}"
        );
    }
}

fn vm_hwm(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib << 10)
}

/// Runs `isovox import ARGS`, watching its memory and time.
fn import(args: &[&std::ffi::OsStr]) -> Outcome {
    let start = Instant::now();
    let mut child = Command::new(isovox())
        .arg("import")
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the isovox binary starts");
    let pid = child.id();
    let limit = rustix::process::Rlimit {
        current: Some(ADDRESS_SPACE),
        maximum: Some(ADDRESS_SPACE),
    };
    rustix::process::prlimit(
        rustix::process::Pid::from_raw(pid as i32),
        rustix::process::Resource::As,
        limit,
    )
    .expect("an address-space limit on the child");
    let mut stderr = child.stderr.take().expect("piped");
    let drain = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = stderr.read_to_string(&mut s);
        s
    });
    let mut peak = 0;
    let mut killed = None;
    let status = loop {
        if let Some(hwm) = vm_hwm(pid) {
            peak = peak.max(hwm);
        }
        if let Some(status) = child.try_wait().expect("wait for the child") {
            break status;
        }
        if killed.is_none() {
            if peak > KILL_AT {
                killed = Some(format!("resident memory passed {} MiB", KILL_AT >> 20));
            } else if start.elapsed() > HANG_GUARD {
                killed = Some(format!("still running after {HANG_GUARD:?}"));
            }
            if killed.is_some() {
                let _ = child.kill();
            }
        }
        // Sampled often: a child that ends between two samples had no time to touch much
        // memory (resident pages are the ones written), so its last sample stands for its peak.
        std::thread::sleep(Duration::from_millis(1));
    };
    let outcome = Outcome {
        code: status.code(),
        stderr: drain.join().expect("the stderr thread"),
        peak,
        elapsed: start.elapsed(),
        killed,
    };
    // Shown with --nocapture: the figures the report quotes.
    eprintln!(
        "isovox import {args:?}: status {:?}, {:.2} s, peak {} MiB{}\n  {}",
        outcome.code,
        outcome.elapsed.as_secs_f64(),
        outcome.peak >> 20,
        outcome
            .killed
            .as_deref()
            .map(|k| format!(", killed: {k}"))
            .unwrap_or_default(),
        outcome.stderr.trim()
    );
    outcome
}

fn os(p: &Path) -> &std::ffi::OsStr {
    p.as_os_str()
}

fn out_vod(dir: &Path) -> PathBuf {
    dir.join("out.vod")
}

fn write(path: &Path, bytes: &[u8]) {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).unwrap();
    }
    std::fs::write(path, bytes).unwrap();
}

// ---- Inputs --------------------------------------------------------------------------------

/// A zstd frame that declares `declared` bytes and holds them: RLE blocks of 128 KiB of
/// zeros, four bytes each (so 12 GiB take 393 KB), with a 1 MiB window.
fn zstd_bomb(declared: u64) -> Vec<u8> {
    const BLOCK: u64 = 128 << 10;
    let blocks = declared.div_ceil(BLOCK);
    let mut f = Vec::with_capacity(14 + 4 * blocks as usize);
    f.extend_from_slice(&0xFD2F_B528u32.to_le_bytes());
    // Frame header descriptor: an 8-byte content size, not single-segment, no checksum.
    f.push(0b1100_0000);
    // Window descriptor: 2^(10 + 10) bytes.
    f.push(10 << 3);
    f.extend_from_slice(&declared.to_le_bytes());
    for i in 0..blocks {
        let size = BLOCK.min(declared - i * BLOCK) as u32;
        let last = u32::from(i + 1 == blocks);
        let header = last | (1 << 1) | (size << 3);
        f.extend_from_slice(&header.to_le_bytes()[..3]);
        f.push(0);
    }
    f
}

/// `len` zeros, gzip-compressed.
fn gzip_zeros(len: u64) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    let zeros = vec![0u8; 1 << 20];
    let mut left = len;
    while left > 0 {
        let n = left.min(zeros.len() as u64) as usize;
        e.write_all(&zeros[..n]).unwrap();
        left -= n as u64;
    }
    e.finish().unwrap()
}

/// `len` zeros as a blosc buffer (lz4, as zarrs writes it).
fn blosc_zeros(len: usize) -> Vec<u8> {
    use zarrs::array::codec::{BloscCodec, BytesToBytesCodecTraits, CodecOptions};
    let configuration = serde_json::from_str(
        r#"{"cname": "lz4", "clevel": 9, "shuffle": "noshuffle", "typesize": 1, "blocksize": 0}"#,
    )
    .unwrap();
    let codec = BloscCodec::new_with_configuration(&configuration).unwrap();
    codec
        .encode(
            std::borrow::Cow::Owned(vec![0u8; len]),
            &CodecOptions::default(),
        )
        .unwrap()
        .into_owned()
}

/// A Zarr v3 uint8 array of 64^3 in one chunk (256 KiB), compressed by `codec` (a v3 codec
/// object), its chunk `c/0/0/0` holding `chunk`.
fn zarr_v3(dir: &Path, codec: &str, chunk: &[u8]) {
    zarr_v3_codecs(
        dir,
        &format!(r#"[{{"name": "bytes", "configuration": {{"endian": "little"}}}}, {codec}]"#),
        chunk,
    );
}

/// [`zarr_v3`] with the whole list of codecs given.
fn zarr_v3_codecs(dir: &Path, codecs: &str, chunk: &[u8]) {
    write(
        &dir.join("zarr.json"),
        format!(
            r#"{{"zarr_format": 3, "node_type": "array", "shape": [64, 64, 64], "data_type": "uint8",
                "chunk_grid": {{"name": "regular", "configuration": {{"chunk_shape": [64, 64, 64]}}}},
                "chunk_key_encoding": {{"name": "default", "configuration": {{"separator": "/"}}}},
                "fill_value": 0, "codecs": {codecs}}}"#
        )
        .as_bytes(),
    );
    write(&dir.join("c/0/0/0"), chunk);
}

/// A Zarr v2 uint8 array of 64^3 in one chunk, compressed by `compressor` (a numcodecs
/// object), its chunk `0.0.0` holding `chunk`.
fn zarr_v2(dir: &Path, compressor: &str, chunk: &[u8]) {
    write(
        &dir.join(".zarray"),
        format!(
            r#"{{"zarr_format": 2, "shape": [64, 64, 64], "chunks": [64, 64, 64], "dtype": "|u1",
                "compressor": {compressor}, "fill_value": 0, "filters": null, "order": "C"}}"#
        )
        .as_bytes(),
    );
    write(&dir.join("0.0.0"), chunk);
}

/// A valid uncompressed Zarr v3 array of 16^3 uint8 at `dir`.
fn small_zarr(dir: &Path) {
    write(
        &dir.join("zarr.json"),
        br#"{"zarr_format": 3, "node_type": "array", "shape": [16, 16, 16], "data_type": "uint8",
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [16, 16, 16]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": 0, "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}]}"#,
    );
    write(&dir.join("c/0/0/0"), &[7u8; 16 * 16 * 16]);
}

/// An OME-Zarr 0.5 group whose only dataset is at `path`.
fn ome_group(dir: &Path, path: &str) {
    write(
        &dir.join("zarr.json"),
        format!(
            r#"{{"zarr_format": 3, "node_type": "group", "attributes": {{"ome": {{"version": "0.5",
                "multiscales": [{{"axes": [{{"name": "z"}}, {{"name": "y"}}, {{"name": "x"}}],
                "datasets": [{{"path": "{path}", "coordinateTransformations": [{{"type": "scale", "scale": [1, 1, 1]}}]}}]}}]}}}}}}"#
        )
        .as_bytes(),
    );
}

/// A NIfTI-1 header (348 bytes, little endian) for `dims` of `datatype` (NIfTI's code, of
/// `bits`), voxels from byte 352; the four bytes of an empty extension follow it.
fn nifti_header(dims: [i16; 3], datatype: i16, bits: i16) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim = [3i16, dims[0], dims[1], dims[2], 1, 1, 1, 1];
    for (i, d) in dim.iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    h[70..72].copy_from_slice(&datatype.to_le_bytes());
    h[72..74].copy_from_slice(&bits.to_le_bytes());
    for i in 0..4 {
        h[76 + 4 * i..80 + 4 * i].copy_from_slice(&1f32.to_le_bytes());
    }
    h[108..112].copy_from_slice(&352f32.to_le_bytes());
    h[112..116].copy_from_slice(&1f32.to_le_bytes());
    h[344..348].copy_from_slice(b"n+1\0");
    h
}

fn gzip(bytes: &[u8], level: flate2::Compression) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), level);
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// Bytes that do not compress.
fn noise(len: usize) -> Vec<u8> {
    let mut x = 0x9E37_79B9_7F4A_7C15u64;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

// ---- A static http server ------------------------------------------------------------------

/// Serves the files under a directory over http on 127.0.0.1 (GET only, one request per
/// connection), recording every path asked for. Lives as long as the test process.
struct FileServer {
    base: String,
    asked: Arc<Mutex<Vec<String>>>,
}

impl FileServer {
    fn start(root: &Path) -> FileServer {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let base = format!("http://{}", listener.local_addr().unwrap());
        let asked = Arc::new(Mutex::new(Vec::new()));
        let (root, log) = (root.to_path_buf(), asked.clone());
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut stream) = stream else { continue };
                let Ok(clone) = stream.try_clone() else {
                    continue;
                };
                let mut reader = BufReader::new(clone);
                let mut request = String::new();
                if reader.read_line(&mut request).is_err() {
                    continue;
                }
                loop {
                    let mut line = String::new();
                    match reader.read_line(&mut line) {
                        Ok(0) | Err(_) => break,
                        Ok(_) if line == "\r\n" => break,
                        Ok(_) => {}
                    }
                }
                let path = request.split_whitespace().nth(1).unwrap_or("/").to_string();
                log.lock().unwrap().push(path.clone());
                // The server itself never leaves its root, whatever it is asked.
                let body = if path.split('/').any(|s| s == "..") {
                    None
                } else {
                    std::fs::read(root.join(path.trim_start_matches('/'))).ok()
                };
                let _ = match body {
                    Some(body) => stream
                        .write_all(
                            format!(
                                "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                                body.len()
                            )
                            .as_bytes(),
                        )
                        .and_then(|()| stream.write_all(&body)),
                    None => stream.write_all(
                        b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
                    ),
                };
            }
        });
        FileServer { base, asked }
    }

    fn asked(&self) -> Vec<String> {
        self.asked.lock().unwrap().clone()
    }
}

// ---- Decompression bombs -------------------------------------------------------------------

#[test]
fn a_zstd_bomb_in_a_zarr_v3_chunk_is_refused_within_the_chunk_size() {
    // 12 GiB declared (and held) in a 393 KB chunk of a 256 KiB array.
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("bomb.zarr");
    zarr_v3(
        &input,
        r#"{"name": "zstd", "configuration": {"level": 1, "checksum": false}}"#,
        &zstd_bomb(12 << 30),
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["bomb.zarr", "c/0/0/0", "more than the 262144 bytes"]);
    assert!(!out_vod(dir.path()).exists());
}

#[test]
fn a_zstd_bomb_inside_a_shard_is_refused_within_the_inner_chunk_size() {
    // One shard of one inner chunk: the bomb, then the index (offset and size, u64 LE).
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("sharded.zarr");
    let mut shard = zstd_bomb(12 << 30);
    let len = shard.len() as u64;
    shard.extend_from_slice(&0u64.to_le_bytes());
    shard.extend_from_slice(&len.to_le_bytes());
    zarr_v3_codecs(
        &input,
        r#"[{"name": "sharding_indexed", "configuration": {"chunk_shape": [64, 64, 64],
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}},
                       {"name": "zstd", "configuration": {"level": 1, "checksum": false}}],
            "index_codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
            "index_location": "end"}}]"#,
        &shard,
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["sharded.zarr", "c/0/0/0", "more than the 262144 bytes"]);
}

#[test]
fn a_zstd_bomb_in_a_zarr_v2_chunk_is_refused_within_the_chunk_size() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("bomb2.zarr");
    zarr_v2(
        &input,
        r#"{"id": "zstd", "level": 1}"#,
        &zstd_bomb(12 << 30),
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["bomb2.zarr", "0.0.0", "more than the 262144 bytes"]);
}

#[test]
fn a_gzip_bomb_in_a_zarr_chunk_is_refused_within_the_chunk_size() {
    // 1 GiB of zeros in about 1 MB.
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("gz.zarr");
    zarr_v3(
        &input,
        r#"{"name": "gzip", "configuration": {"level": 9}}"#,
        &gzip_zeros(1 << 30),
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["gz.zarr", "c/0/0/0", "gzip", "more than the 262144 bytes"]);
}

#[test]
fn a_blosc_bomb_in_a_zarr_v2_chunk_is_refused_before_it_is_decoded() {
    // 1 GiB of zeros in a few megabytes of blosc (lz4).
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("blosc.zarr");
    zarr_v2(
        &input,
        r#"{"id": "blosc", "cname": "lz4", "clevel": 9, "shuffle": 0, "blocksize": 0}"#,
        &blosc_zeros(1 << 30),
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&[
        "blosc.zarr",
        "0.0.0",
        "blosc data declares 1073741824 bytes",
    ]);
}

#[test]
fn zstd_bombs_served_over_http_are_refused_within_the_chunk_size() {
    // 12 GiB take 393 KB, more than one encoded chunk of the array can be: refused while it
    // arrives. 4 GiB take 131 KB, which could be a chunk: refused while it is decoded.
    for (declared, why) in [
        (12u64 << 30, "bytes expected"),
        (4 << 30, "zstd data decodes to more than the 262144 bytes"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        zarr_v3(
            &dir.path().join("bomb.zarr"),
            r#"{"name": "zstd", "configuration": {"level": 1, "checksum": false}}"#,
            &zstd_bomb(declared),
        );
        let server = FileServer::start(dir.path());
        let url = format!("{}/bomb.zarr", server.base);
        let out = import(&[url.as_ref(), "-o".as_ref(), os(&out_vod(dir.path()))]);
        out.assert_refused(&[&url, "c/0/0/0", "more than the", why]);
    }
}

#[test]
fn a_gzip_bomb_in_a_precomputed_chunk_is_refused_within_the_chunk_size() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("pc");
    write(
        &input.join("info"),
        br#"{"type": "image", "data_type": "uint8", "num_channels": 1, "scales": [{"key": "s0",
            "size": [64, 64, 64], "resolution": [1, 1, 1], "voxel_offset": [0, 0, 0],
            "chunk_sizes": [[64, 64, 64]], "encoding": "raw"}]}"#,
    );
    write(&input.join("s0/0-64_0-64_0-64.gz"), &gzip_zeros(1 << 30));
    let out = import(&[
        "--from".as_ref(),
        "precomputed".as_ref(),
        os(&input),
        "-o".as_ref(),
        os(&out_vod(dir.path())),
    ]);
    out.assert_refused(&["0-64_0-64_0-64.gz", "more than the 262144 bytes"]);
}

// ---- Headers that lie ----------------------------------------------------------------------

#[test]
fn a_nifti_header_promising_more_than_its_file_is_refused_before_reading() {
    // u16 8190^3 (1 TiB) in a 352-byte file.
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("liar.nii");
    write(&input, &nifti_header([8190; 3], 512, 16));
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["liar.nii", "8190 x 8190 x 8190", "the file has 352 bytes"]);
    assert!(
        out.elapsed < Duration::from_secs(5),
        "refused before reading, not after: {out:#?}"
    );
}

#[test]
fn a_lying_f64_nifti_with_a_window_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("liar64.nii");
    write(&input, &nifti_header([5100; 3], 64, 64));
    let out = import(&[
        os(&input),
        "--window".as_ref(),
        "0,1".as_ref(),
        "-o".as_ref(),
        os(&out_vod(dir.path())),
    ]);
    out.assert_refused(&[
        "liar64.nii",
        "5100 x 5100 x 5100 float64",
        "the file has 352 bytes",
    ]);
}

#[test]
fn a_gzip_nifti_promising_more_than_deflate_can_hold_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("liar.nii.gz");
    write(
        &input,
        &gzip(
            &nifti_header([8190; 3], 512, 16),
            flate2::Compression::best(),
        ),
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["liar.nii.gz", "8190 x 8190 x 8190", "gzip can hold"]);
}

#[test]
fn a_truncated_gzip_nifti_stops_the_import_when_its_voxels_end() {
    // 1024^3 u8 promised (1 GiB), a little over 1 MB of incompressible voxels given: enough
    // bytes of gzip that deflate could hold the promise, so only reading finds the lie. The
    // first slab (32 planes) fails; nothing is built after it.
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("short.nii.gz");
    let mut file = nifti_header([1024; 3], 2, 8);
    file.extend_from_slice(&noise(1_100_000));
    write(&input, &gzip(&file, flate2::Compression::none()));
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["short.nii.gz", "truncated", "before plane 32 of 1024"]);
    assert!(!out_vod(dir.path()).exists());
}

#[test]
fn raw_dims_beyond_the_file_are_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("small.raw");
    write(&input, &[1u8; 1 << 20]);
    let out = import(&[
        os(&input),
        "--dims".as_ref(),
        "8190,8190,8190".as_ref(),
        "--type".as_ref(),
        "u16".as_ref(),
        "-o".as_ref(),
        os(&out_vod(dir.path())),
    ]);
    out.assert_refused(&["small.raw", "1048576 voxel bytes"]);
}

/// A one-page little-endian TIFF of `w` x `h` u16 in one uncompressed strip of
/// `strip_bytes` at offset 8 + the IFD, the file ending right after the IFD.
fn lying_tiff(w: u32, h: u32, strip_bytes: u32) -> Vec<u8> {
    let entries: [(u16, u16, u32); 9] = [
        (256, 4, w),           // ImageWidth, LONG
        (257, 4, h),           // ImageLength
        (258, 3, 16),          // BitsPerSample, SHORT
        (259, 3, 1),           // Compression: none
        (262, 3, 1),           // Photometric: black is zero
        (273, 4, 0),           // StripOffsets (patched below)
        (277, 3, 1),           // SamplesPerPixel
        (278, 4, h),           // RowsPerStrip
        (279, 4, strip_bytes), // StripByteCounts
    ];
    let ifd_len = 2 + 12 * entries.len() + 4;
    let data_at = (8 + ifd_len) as u32;
    let mut t = b"II*\0".to_vec();
    t.extend_from_slice(&8u32.to_le_bytes());
    t.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, kind, value) in entries {
        let value = if tag == 273 { data_at } else { value };
        t.extend_from_slice(&tag.to_le_bytes());
        t.extend_from_slice(&kind.to_le_bytes());
        t.extend_from_slice(&1u32.to_le_bytes());
        if kind == 3 {
            t.extend_from_slice(&(value as u16).to_le_bytes());
            t.extend_from_slice(&[0, 0]);
        } else {
            t.extend_from_slice(&value.to_le_bytes());
        }
    }
    t.extend_from_slice(&0u32.to_le_bytes());
    // A few voxels of the promised strip.
    t.extend_from_slice(&[0u8; 64]);
    t
}

#[test]
fn a_tiff_strip_beyond_the_file_is_refused_naming_its_page_and_strip() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("liar.tif");
    write(&input, &lying_tiff(4096, 4096, 4096 * 4096 * 2));
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&[
        "liar.tif",
        "page 0, strip 0",
        "run past the end of the file",
    ]);
}

// ---- Paths that leave the import root ------------------------------------------------------

#[test]
fn an_ome_zarr_dataset_path_outside_the_image_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    // What the path leads to is a valid array, so following it would succeed.
    small_zarr(&dir.path().join("outside"));
    for path in ["../outside", "../../outside", "/outside", "%2e%2e/outside"] {
        let image = dir.path().join("img.zarr");
        let _ = std::fs::remove_dir_all(&image);
        ome_group(&image, path);
        let out = import(&[os(&image), "-o".as_ref(), os(&out_vod(dir.path()))]);
        out.assert_refused(&["img.zarr", &format!("{path:?}"), "leads outside the image"]);
        assert!(!out_vod(dir.path()).exists(), "{path}");
    }
}

#[test]
fn an_ome_zarr_dataset_path_outside_the_url_prefix_is_refused_and_not_fetched() {
    let dir = tempfile::tempdir().unwrap();
    small_zarr(&dir.path().join("outside"));
    ome_group(&dir.path().join("img.zarr"), "../outside");
    let server = FileServer::start(dir.path());
    let url = format!("{}/img.zarr", server.base);
    let out = import(&[url.as_ref(), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&[&url, "\"../outside\"", "leads outside the image"]);
    let asked = server.asked();
    assert!(
        asked.iter().all(|p| p.starts_with("/img.zarr/")),
        "a request outside the prefix: {asked:?}"
    );
}

#[test]
fn a_precomputed_scale_key_outside_the_volume_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("pc");
    write(
        &input.join("info"),
        br#"{"type": "image", "data_type": "uint8", "num_channels": 1, "scales": [{"key": "../x",
            "size": [16, 16, 16], "resolution": [1, 1, 1], "voxel_offset": [0, 0, 0],
            "chunk_sizes": [[16, 16, 16]], "encoding": "raw"}]}"#,
    );
    // A chunk where the key leads, so following it would succeed.
    write(&dir.path().join("x/0-16_0-16_0-16"), &[3u8; 16 * 16 * 16]);
    let out = import(&[
        "--from".as_ref(),
        "precomputed".as_ref(),
        os(&input),
        "-o".as_ref(),
        os(&out_vod(dir.path())),
    ]);
    out.assert_refused(&["info", "\"../x\"", "leads outside the volume"]);
}

// ---- Messages ------------------------------------------------------------------------------

#[test]
fn a_file_named_nii_gz_that_is_not_nifti_says_what_was_expected() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("x.nii.gz");
    write(
        &input,
        "this is a text file, not a volume\n".repeat(20).as_bytes(),
    );
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["x.nii.gz", "not a NIfTI-1 header", "magic"]);
    assert!(!out.stderr.contains("--dims"), "{out:#?}");
}

#[test]
fn a_constant_input_of_huge_values_is_named_in_few_digits() {
    // A valid f64 NIfTI whose every voxel is 1e308: the percentile window cannot be taken.
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("huge.nii");
    let mut file = nifti_header([8; 3], 64, 64);
    for _ in 0..8 * 8 * 8 {
        file.extend_from_slice(&1e308f64.to_le_bytes());
    }
    write(&input, &file);
    let out = import(&[os(&input), "-o".as_ref(), os(&out_vod(dir.path()))]);
    out.assert_refused(&["huge.nii", "both 1e308", "--window"]);
}

// ---- What is valid still imports -----------------------------------------------------------

/// 64^3 u8 voxels, x fastest, that compress somewhat and differ from plane to plane.
fn voxels() -> Vec<u8> {
    (0..64 * 64 * 64u32)
        .map(|i| ((i % 64 / 8 + i / 4096) * 7 % 251) as u8)
        .collect()
}

/// The chunk of `data` (64^3, x fastest) at chunk position (x, y, z), of `edge`^3, x fastest.
fn chunk_of(data: &[u8], edge: usize, [cx, cy, cz]: [usize; 3]) -> Vec<u8> {
    let mut out = Vec::with_capacity(edge * edge * edge);
    for z in cz * edge..(cz + 1) * edge {
        for y in cy * edge..(cy + 1) * edge {
            let at = (z * 64 + y) * 64 + cx * edge;
            out.extend_from_slice(&data[at..at + edge]);
        }
    }
    out
}

/// A Zarr v3 array of `data` (64^3 uint8) at `dir`, chunks of `chunk`^3 encoded by `codecs`,
/// written by zarrs as another program would write it.
fn zarrs_array(dir: &Path, chunk: u64, codecs: &str, data: &[u8]) {
    use zarrs::array::{Array, ArrayMetadata};
    std::fs::create_dir_all(dir).unwrap();
    let metadata: ArrayMetadata = serde_json::from_str(&format!(
        r#"{{"zarr_format": 3, "node_type": "array", "shape": [64, 64, 64], "data_type": "uint8",
            "chunk_grid": {{"name": "regular", "configuration": {{"chunk_shape": [{chunk}, {chunk}, {chunk}]}}}},
            "chunk_key_encoding": {{"name": "default", "configuration": {{"separator": "/"}}}},
            "fill_value": 0, "codecs": {codecs}}}"#
    ))
    .unwrap();
    let store = Arc::new(zarrs::filesystem::FilesystemStore::new(dir).unwrap());
    let array = Array::new_with_metadata(store, "/", metadata).unwrap();
    array.store_metadata().unwrap();
    array
        .store_array_subset_elements::<u8>(&array.subset_all(), data)
        .unwrap();
}

/// Imports `input` (with `extra` arguments) and asserts that it succeeds within the memory
/// bound and that the volume's voxels are `expected`.
fn imports_as(input: &std::ffi::OsStr, extra: &[&str], dir: &Path, expected: &[u8]) {
    let vod = dir.join("ok.vod");
    let _ = std::fs::remove_file(&vod);
    let mut args = vec![input];
    args.extend(extra.iter().map(|a| std::ffi::OsStr::new(*a)));
    args.extend(["-o".as_ref(), vod.as_os_str()]);
    let out = import(&args);
    assert_eq!(out.code, Some(0), "{out:#?}");
    assert!(out.peak < PEAK_BOUND, "{out:#?}");
    let raw = dir.join("ok.raw");
    let exported = Command::new(isovox())
        .arg("export")
        .args([
            os(&vod),
            "-o".as_ref(),
            os(&raw),
            "--format".as_ref(),
            "raw".as_ref(),
        ])
        .output()
        .unwrap();
    assert!(exported.status.success(), "{exported:?}");
    assert!(
        std::fs::read(&raw).unwrap() == expected,
        "{input:?}: the imported voxels differ"
    );
}

#[test]
fn valid_zarr_arrays_import_whatever_their_codec() {
    let data = voxels();
    let dir = tempfile::tempdir().unwrap();
    let bytes = r#"{"name": "bytes", "configuration": {"endian": "little"}}"#;
    for (name, chunk, codecs) in [
        (
            "zstd",
            32,
            format!(
                r#"[{bytes}, {{"name": "zstd", "configuration": {{"level": 3, "checksum": true}}}}]"#
            ),
        ),
        (
            "gzip",
            32,
            format!(r#"[{bytes}, {{"name": "gzip", "configuration": {{"level": 5}}}}]"#),
        ),
        (
            "blosc",
            32,
            format!(
                r#"[{bytes}, {{"name": "blosc", "configuration": {{"cname": "zstd", "clevel": 5, "shuffle": "noshuffle", "typesize": 1, "blocksize": 0}}}}]"#
            ),
        ),
        (
            "sharded",
            64,
            format!(
                r#"[{{"name": "sharding_indexed", "configuration": {{"chunk_shape": [16, 16, 16],
            "codecs": [{bytes}, {{"name": "zstd", "configuration": {{"level": 3, "checksum": false}}}}],
            "index_codecs": [{bytes}, {{"name": "crc32c"}}], "index_location": "end"}}}}]"#
            ),
        ),
    ] {
        let input = dir.path().join(format!("{name}.zarr"));
        zarrs_array(&input, chunk, &codecs, &data);
        imports_as(os(&input), &[], dir.path(), &data);
    }
    // Zarr v2 with zstd (frames with their content size) and zlib, chunks by hand.
    for (name, compressor) in [
        ("v2zstd", r#"{"id": "zstd", "level": 3}"#),
        ("v2zlib", r#"{"id": "zlib", "level": 5}"#),
    ] {
        let input = dir.path().join(format!("{name}.zarr"));
        write(
            &input.join(".zarray"),
            format!(
                r#"{{"zarr_format": 2, "shape": [64, 64, 64], "chunks": [32, 32, 32], "dtype": "|u1",
                    "compressor": {compressor}, "fill_value": 0, "filters": null, "order": "C"}}"#
            )
            .as_bytes(),
        );
        for c in 0..8 {
            let [cx, cy, cz] = [c % 2, c / 2 % 2, c / 4];
            let raw = chunk_of(&data, 32, [cx, cy, cz]);
            let encoded = if name == "v2zstd" {
                zstd::bulk::compress(&raw, 3).unwrap()
            } else {
                let mut e =
                    flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::new(5));
                e.write_all(&raw).unwrap();
                e.finish().unwrap()
            };
            write(&input.join(format!("{cz}.{cy}.{cx}")), &encoded);
        }
        imports_as(os(&input), &[], dir.path(), &data);
    }
}

#[test]
fn a_valid_ome_zarr_imports_locally_and_over_http() {
    let data = voxels();
    let dir = tempfile::tempdir().unwrap();
    let image = dir.path().join("img.zarr");
    ome_group(&image, "0");
    zarrs_array(
        &image.join("0"),
        32,
        r#"[{"name": "bytes", "configuration": {"endian": "little"}}, {"name": "zstd", "configuration": {"level": 3, "checksum": false}}]"#,
        &data,
    );
    imports_as(os(&image), &[], dir.path(), &data);
    let server = FileServer::start(dir.path());
    let url = format!("{}/img.zarr", server.base);
    imports_as(url.as_ref(), &[], dir.path(), &data);
    assert!(server.asked().iter().all(|p| p.starts_with("/img.zarr/")));
}

#[test]
fn valid_nifti_tiff_and_precomputed_inputs_import() {
    let data = voxels();
    let dir = tempfile::tempdir().unwrap();
    let mut nifti = nifti_header([64; 3], 2, 8);
    nifti.extend_from_slice(&data);
    let plain = dir.path().join("ok.nii");
    write(&plain, &nifti);
    imports_as(os(&plain), &[], dir.path(), &data);
    let gz = dir.path().join("ok.nii.gz");
    write(&gz, &gzip(&nifti, flate2::Compression::default()));
    imports_as(os(&gz), &[], dir.path(), &data);

    let tif = dir.path().join("ok.tif");
    {
        let mut e = tiff::encoder::TiffEncoder::new(std::fs::File::create(&tif).unwrap()).unwrap();
        for plane in data.chunks(64 * 64) {
            e.write_image::<tiff::encoder::colortype::Gray8>(64, 64, plane)
                .unwrap();
        }
    }
    imports_as(os(&tif), &[], dir.path(), &data);

    let pc = dir.path().join("pc");
    write(
        &pc.join("info"),
        br#"{"type": "image", "data_type": "uint8", "num_channels": 1, "scales": [{"key": "s0",
            "size": [64, 64, 64], "resolution": [1, 1, 1], "voxel_offset": [0, 0, 0],
            "chunk_sizes": [[32, 32, 32]], "encoding": "raw"}]}"#,
    );
    for c in 0..8 {
        let [cx, cy, cz] = [c % 2, c / 2 % 2, c / 4];
        let name = format!(
            "s0/{}-{}_{}-{}_{}-{}.gz",
            cx * 32,
            cx * 32 + 32,
            cy * 32,
            cy * 32 + 32,
            cz * 32,
            cz * 32 + 32
        );
        write(
            &pc.join(name),
            &gzip(
                &chunk_of(&data, 32, [cx, cy, cz]),
                flate2::Compression::default(),
            ),
        );
    }
    imports_as(os(&pc), &["--from", "precomputed"], dir.path(), &data);
}
