//! Where an input lives: a local path or an http(s) URL, read file by file.
//!
//! Neuroglancer-style prefixes (`precomputed://`, `zarr://`, `zarr2://`, `zarr3://`) are
//! accepted and name the format. A file may be gzip-compressed: a local `NAME.gz` beside a
//! missing `NAME` (how cloud-volume writes gzip chunks to disk), or an http answer with
//! `Content-Encoding: gzip`. Every read has a size bound, decompression included.

use crate::formats::FormatsError;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A local directory or file, or an http(s) URL (TLS by rustls, trusting the system's
/// certificate store).
#[derive(Debug, Clone)]
pub enum Location {
    /// A local path.
    Local(PathBuf),
    /// An http(s) URL.
    Http {
        /// The client every request goes through.
        client: reqwest::blocking::Client,
        /// Without a trailing slash.
        base: String,
    },
}

/// The format a location's prefix names, and the location without it.
pub fn strip_prefix(input: &str) -> (Option<&'static str>, &str) {
    for (prefix, format) in [
        ("precomputed://", "precomputed"),
        ("zarr3://", "zarr"),
        ("zarr2://", "zarr"),
        ("zarr://", "zarr"),
        ("nifti://", "nifti"),
        ("tiff://", "tiff"),
    ] {
        if let Some(rest) = input.strip_prefix(prefix) {
            return (Some(format), rest);
        }
    }
    (None, input)
}

impl Location {
    /// The location `input` names (without a format prefix).
    ///
    /// # Errors
    /// A scheme other than http, https and file.
    pub fn parse(input: &str) -> Result<Location, FormatsError> {
        if input.starts_with("http://") || input.starts_with("https://") {
            crate::client_tls::install_provider();
            let client = reqwest::blocking::Client::builder()
                .connect_timeout(Duration::from_secs(10))
                .timeout(Duration::from_secs(120))
                .build()
                .map_err(|e| FormatsError::Fetch {
                    url: input.into(),
                    detail: e.to_string(),
                })?;
            return Ok(Location::Http {
                client,
                base: input.trim_end_matches('/').to_string(),
            });
        }
        if let Some(path) = input.strip_prefix("file://") {
            return Ok(Location::Local(PathBuf::from(path)));
        }
        if input.contains("://") {
            return Err(FormatsError::input(format!(
                "{input}: unknown scheme (a local path or an http URL is expected)"
            )));
        }
        Ok(Location::Local(PathBuf::from(input)))
    }

    /// The local path, if it is one.
    pub fn path(&self) -> Option<&Path> {
        match self {
            Location::Local(p) => Some(p),
            Location::Http { .. } => None,
        }
    }

    /// How to name `rel` in messages.
    pub fn describe(&self, rel: &str) -> String {
        match self {
            Location::Local(p) => p.join(rel).display().to_string(),
            Location::Http { base, .. } => format!("{base}/{rel}"),
        }
    }

    /// The location or its URL as text (for messages).
    pub fn as_str(&self) -> String {
        match self {
            Location::Local(p) => p.display().to_string(),
            Location::Http { base, .. } => base.clone(),
        }
    }

    /// The bytes of `rel` (decompressed when gzip), or `None` when there is no such file.
    ///
    /// # Errors
    /// A read or a request fails, the server answers other than 200/404, or the bytes exceed
    /// `max_bytes`.
    pub fn get(&self, rel: &str, max_bytes: u64) -> Result<Option<Vec<u8>>, FormatsError> {
        // The readers check the paths they take from metadata with a better message; this is
        // the last line, for whatever name reaches here.
        let rel = contained(rel).map_err(|why| {
            FormatsError::input(format!(
                "{}: {rel:?} leads outside it ({why})",
                self.as_str()
            ))
        })?;
        match self {
            Location::Local(root) => {
                let path = root.join(rel);
                match std::fs::File::open(&path) {
                    Ok(f) => read_bounded(f, max_bytes, &path.display().to_string()).map(Some),
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                        let gz = crate::store::build::sibling(&path, ".gz");
                        match std::fs::File::open(&gz) {
                            Ok(f) => read_bounded(
                                flate2::read::GzDecoder::new(std::io::BufReader::new(f)),
                                max_bytes,
                                &gz.display().to_string(),
                            )
                            .map(Some),
                            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
                            Err(e) => Err(FormatsError::io_path("cannot open", &gz)(e)),
                        }
                    }
                    Err(e) => Err(FormatsError::io_path("cannot open", &path)(e)),
                }
            }
            Location::Http { client, base } => {
                let url = format!("{base}/{rel}");
                let fetch_error = |detail: String| FormatsError::Fetch {
                    url: url.clone(),
                    detail,
                };
                let response = client
                    .get(&url)
                    .send()
                    .map_err(|e| fetch_error(crate::store::error_chain(&e)))?;
                let status = response.status();
                if status == reqwest::StatusCode::NOT_FOUND {
                    return Ok(None);
                }
                if !status.is_success() {
                    return Err(fetch_error(format!("the server answered {status}")));
                }
                let gzip = response
                    .headers()
                    .get(reqwest::header::CONTENT_ENCODING)
                    .is_some_and(|v| v.as_bytes().eq_ignore_ascii_case(b"gzip"));
                if gzip {
                    read_bounded(flate2::read::GzDecoder::new(response), max_bytes, &url).map(Some)
                } else {
                    read_bounded(response, max_bytes, &url).map(Some)
                }
            }
        }
    }
}

/// `rel` (a path an input's metadata names: an OME-Zarr dataset, a precomputed scale key, a
/// chunk) without its outer slashes, if it stays under the location it is relative to, locally
/// and as a URL path: no `.` or `..` segment (percent-encoded or not, as URL parsers decode
/// them), no leading slash, backslash, scheme or drive, query or fragment.
///
/// # Errors
/// Why `rel` may lead elsewhere.
pub fn contained(rel: &str) -> Result<&str, String> {
    if rel.starts_with('/') {
        return Err("an absolute path".into());
    }
    if let Some(c) = rel
        .chars()
        .find(|c| matches!(c, '\\' | '?' | '#' | ':') || c.is_control())
    {
        return Err(format!("{c:?} in a relative path"));
    }
    for segment in rel.trim_end_matches('/').split('/') {
        let decoded = percent_decoded(segment);
        if decoded == "." || decoded == ".." {
            return Err(format!("a {segment:?} segment"));
        }
        if decoded.contains(['/', '\\', '\0']) {
            return Err(format!("an encoded separator in {segment:?}"));
        }
    }
    Ok(rel.trim_end_matches('/'))
}

/// `s` with its `%XX` escapes decoded (as bytes, lossily as text).
fn percent_decoded(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = |c: u8| (c as char).to_digit(16);
        match (
            b[i],
            b.get(i + 1).copied().and_then(hex),
            b.get(i + 2).copied().and_then(hex),
        ) {
            (b'%', Some(h), Some(l)) => {
                out.push((h * 16 + l) as u8);
                i += 3;
            }
            (c, _, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Reads `r` to its end, refusing more than `max_bytes`.
fn read_bounded(r: impl Read, max_bytes: u64, what: &str) -> Result<Vec<u8>, FormatsError> {
    let mut out = Vec::new();
    r.take(max_bytes.saturating_add(1))
        .read_to_end(&mut out)
        .map_err(|source| FormatsError::Io {
            context: format!("cannot read {what}"),
            source,
        })?;
    if out.len() as u64 > max_bytes {
        return Err(FormatsError::input(format!(
            "{what} holds more than the {max_bytes} bytes expected"
        )));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::contained;

    #[test]
    fn paths_inside_the_location_are_kept() {
        for (rel, kept) in [
            ("0", "0"),
            ("s0/", "s0"),
            ("scale0/image", "scale0/image"),
            ("8_8_8", "8_8_8"),
            ("4_4_40/0-64_0-64_0-16", "4_4_40/0-64_0-64_0-16"),
            ("c/0/0/0", "c/0/0/0"),
            ("0.0.0", "0.0.0"),
            ("..data", "..data"),
            ("a.b/..c", "a.b/..c"),
            ("%41", "%41"),
            ("", ""),
        ] {
            assert_eq!(contained(rel), Ok(kept), "{rel}");
        }
    }

    #[test]
    fn paths_that_leave_the_location_are_refused() {
        for rel in [
            "..",
            "../x",
            "../../x",
            "a/../../x",
            "a/..",
            "./x",
            "a/./b",
            "/etc/passwd",
            "//host/x",
            "%2e%2e/x",
            "%2E%2e",
            ".%2E/x",
            "%2e/x",
            "a/%2f..%2fx",
            "a%2F..",
            "..\\x",
            "a\\..\\..\\x",
            "http://other.example/x",
            "https:x",
            "file:///etc/passwd",
            "C:/Windows",
            "x?y=../z",
            "x#../y",
            "a\0b",
        ] {
            assert!(contained(rel).is_err(), "{rel:?} was kept");
        }
    }
}
