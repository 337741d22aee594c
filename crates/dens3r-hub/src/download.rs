//! One file over HTTP(S) into the cache: asked first without following redirects (the hub's
//! first answer carries the file's SHA-256 and size, the redirect target does not), then
//! streamed into `NAME.part`, resumed from where a cut download stopped (`Range`), checked
//! against the expected SHA-256 and only then renamed to `NAME`. A file that fails the check is
//! removed; a cut one is kept for the next try.

use crate::HubError;
use sha2::{Digest, Sha256};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// How far a download is: bytes in the file so far and the total when known.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Progress {
    /// Bytes of the file written so far (including a resumed part).
    pub done: u64,
    /// The file's size, when the server said.
    pub total: Option<u64>,
}

/// What a finished download was checked against.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Fetched {
    /// The file.
    pub path: PathBuf,
    /// Its SHA-256 (hex).
    pub sha256: String,
    /// Where the expected SHA-256 came from: `"catalogue"`, `"server"` (the hub's
    /// `X-Linked-Etag` / `ETag`) or `"none"` (recorded, not checked).
    pub checked_against: &'static str,
    /// Bytes this call fetched (0 when the file was complete already).
    pub fetched: u64,
    /// The byte offset it resumed from (0 for a fresh download).
    pub resumed_from: u64,
}

/// What the first answer said about the file.
struct Head {
    /// Where to fetch the bytes (the redirect target, or the URL itself).
    location: String,
    /// SHA-256 the server published for the file, if any.
    sha256: Option<String>,
    /// The file's size, if given.
    size: Option<u64>,
}

fn agent(follow_redirects: bool) -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .max_redirects(if follow_redirects { 10 } else { 0 })
        .timeout_connect(Some(Duration::from_secs(30)))
        .timeout_recv_response(Some(Duration::from_secs(60)))
        .timeout_recv_body(Some(Duration::from_secs(120)))
        .build()
        .into()
}

/// A 64-digit hex SHA-256 in an ETag-like header value (quotes and a weak `W/` prefix
/// stripped), lower-cased.
fn sha_in(value: &str) -> Option<String> {
    let v = value.trim().trim_start_matches("W/").trim_matches('"');
    (v.len() == 64 && v.bytes().all(|b| b.is_ascii_hexdigit())).then(|| v.to_ascii_lowercase())
}

/// `location` made absolute against `url` (a redirect may give a path only).
fn absolute(url: &str, location: &str) -> String {
    if location.contains("://") {
        return location.to_string();
    }
    let origin_end = url.find("://").map(|i| url[i + 3..].find('/').map_or(url.len(), |j| i + 3 + j)).unwrap_or(0);
    format!("{}/{}", &url[..origin_end], location.trim_start_matches('/'))
}

fn head(url: &str) -> Result<Head, HubError> {
    let net = |e: ureq::Error| {
        HubError::invalid(format!("{url}: cannot reach the server ({e}); check the connection or $DENS3R_HUB_ENDPOINT"))
    };
    let resp = agent(false).head(url).call().map_err(net)?;
    let header = |n: &str| resp.headers().get(n).and_then(|v| v.to_str().ok()).map(str::to_string);
    let status = resp.status().as_u16();
    let sha256 = header("x-linked-etag").and_then(|v| sha_in(&v)).or_else(|| header("etag").and_then(|v| sha_in(&v)));
    let linked_size = header("x-linked-size").and_then(|v| v.trim().parse().ok());
    match status {
        200..=299 => {
            let size = linked_size.or_else(|| header("content-length").and_then(|v| v.trim().parse().ok()));
            Ok(Head { location: url.to_string(), sha256, size })
        }
        300..=399 => {
            let loc = header("location")
                .ok_or_else(|| HubError::invalid(format!("{url}: a redirect ({status}) without a Location")))?;
            // A redirect's own Content-Length is its empty body's, not the file's.
            Ok(Head { location: absolute(url, &loc), sha256, size: linked_size })
        }
        401 | 403 => Err(HubError::invalid(format!(
            "{url}: the server refused access ({status}); the model may need an account or a licence acceptance on its page"
        ))),
        404 => Err(HubError::invalid(format!("{url}: not found (404); the catalogue entry may be out of date"))),
        _ => Err(HubError::invalid(format!("{url}: the server answered {status}; try again later"))),
    }
}

/// SHA-256 of a file, read in 1 MB blocks.
pub fn sha256_file(path: &Path) -> Result<String, HubError> {
    let mut h = Sha256::new();
    hash_file_into(path, &mut h)?;
    Ok(hex(h))
}

/// Feeds the bytes of `path` to `h`.
fn hash_file_into(path: &Path, h: &mut Sha256) -> Result<(), HubError> {
    let mut f = std::fs::File::open(path).map_err(|e| HubError::file(path, format!("cannot read ({e})")))?;
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| HubError::file(path, format!("cannot read ({e})")))?;
        if n == 0 {
            return Ok(());
        }
        h.update(&buf[..n]);
    }
}

fn hex(h: Sha256) -> String {
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// The partial file of `dest`.
pub fn part_path(dest: &Path) -> PathBuf {
    let mut name = dest.file_name().unwrap_or_default().to_os_string();
    name.push(".part");
    dest.with_file_name(name)
}

/// Downloads `url` to `dest` (its folder must exist), resuming `dest.part` when a previous try
/// was cut, and checks the result against `expected_sha256` (from the catalogue) or else the
/// server's published SHA-256. `progress` is called as bytes arrive.
pub fn download(
    url: &str,
    dest: &Path,
    expected_sha256: Option<&str>,
    progress: &mut dyn FnMut(Progress),
) -> Result<Fetched, HubError> {
    download_checked(url, dest, &Expect { sha256: expected_sha256, ..Expect::default() }, progress)
}

/// A check of a finished file's format: `Err` says what the bytes are instead.
pub type FormatCheck = dyn Fn(&Path) -> Result<(), String>;

/// What a download must be beyond its checksum.
#[derive(Default)]
pub struct Expect<'a> {
    /// SHA-256 from the catalogue (else the server's, if it publishes one).
    pub sha256: Option<&'a str>,
    /// The most bytes the file may have: a larger announced size is refused before anything is
    /// fetched, a body that runs past it is cut off and refused.
    pub max_bytes: Option<u64>,
    /// A check of the finished bytes (their format); a failure removes them.
    pub check: Option<&'a FormatCheck>,
}

/// [`download`] with limits and a format check: a size beyond `max_bytes` or the free disk is
/// refused before anything is fetched, and bytes that fail `check` are removed, never renamed
/// into place (an error page served as the file, a body cut short with no length announced).
pub fn download_checked(
    url: &str,
    dest: &Path,
    expect: &Expect,
    progress: &mut dyn FnMut(Progress),
) -> Result<Fetched, HubError> {
    let expected_sha256 = expect.sha256;
    let head = head(url)?;
    if let (Some(size), Some(max)) = (head.size, expect.max_bytes) {
        if size > max {
            return Err(HubError::invalid(format!(
                "{url}: the server announces {size} bytes, more than the {max} this file can have; \
                 check $DENS3R_HUB_ENDPOINT (a mirror serving something else?)"
            )));
        }
    }
    if let (Some(size), Some(free)) = (head.size, free_bytes(dest.parent().unwrap_or(Path::new(".")))) {
        let have = std::fs::metadata(part_path(dest)).map(|m| m.len()).unwrap_or(0);
        if size.saturating_sub(have) > free {
            return Err(HubError::file(
                dest,
                format!(
                    "needs {size} bytes, and its disk has {free} free; free some space or set ${}",
                    crate::HOME_ENV
                ),
            ));
        }
    }
    let (expected, checked_against) = match (expected_sha256, &head.sha256) {
        (Some(s), _) => (Some(s.to_ascii_lowercase()), "catalogue"),
        (None, Some(s)) => (Some(s.clone()), "server"),
        (None, None) => (None, "none"),
    };
    let part = part_path(dest);
    let mut have = std::fs::metadata(&part).map(|m| m.len()).unwrap_or(0);
    if head.size.is_some_and(|s| have > s) {
        have = 0;
    }
    let resumed_from = have;
    // The hash follows the bytes as they are written; only a part already whole is read back.
    let (fetched, hashed) = if head.size != Some(have) || have == 0 {
        fetch_into(&head.location, &part, &mut have, head.size, expect.max_bytes, progress)?
    } else {
        (0, None)
    };
    let got = match hashed {
        Some(h) => hex(h),
        None => sha256_file(&part)?,
    };
    if let Some(want) = &expected {
        if *want != got {
            let _ = std::fs::remove_file(&part);
            return Err(HubError::file(
                dest,
                format!(
                    "the download does not match its SHA-256 ({checked_against}: {want}, got {got}); it was removed, \
                     run the command again to download it afresh"
                ),
            ));
        }
    }
    if let Some(check) = expect.check {
        if let Err(why) = check(&part) {
            let _ = std::fs::remove_file(&part);
            return Err(HubError::file(
                dest,
                format!(
                    "the server sent {why}, not the file; nothing was kept. Check $DENS3R_HUB_ENDPOINT and run again"
                ),
            ));
        }
    }
    std::fs::rename(&part, dest).map_err(|e| HubError::file(dest, format!("cannot finish the download ({e})")))?;
    Ok(Fetched { path: dest.to_path_buf(), sha256: got, checked_against, fetched, resumed_from })
}

/// Streams `location` into `part` from byte `*have` on; returns the bytes fetched and the
/// SHA-256 state of the whole part (`None`: nothing was fetched, the part is to be hashed). A
/// cut connection leaves what arrived in `part` and says so.
fn fetch_into(
    location: &str,
    part: &Path,
    have: &mut u64,
    total: Option<u64>,
    max_bytes: Option<u64>,
    progress: &mut dyn FnMut(Progress),
) -> Result<(u64, Option<Sha256>), HubError> {
    let net = |e: ureq::Error| {
        HubError::invalid(format!("{location}: cannot reach the server ({e}); check the connection and run again"))
    };
    let mut req = agent(true).get(location);
    if *have > 0 {
        req = req.header("Range", format!("bytes={have}-"));
    }
    let mut resp = req.call().map_err(net)?;
    let status = resp.status().as_u16();
    let append = match status {
        206 => {
            let from = resp
                .headers()
                .get("content-range")
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.trim().strip_prefix("bytes ")?.split('-').next()?.parse::<u64>().ok());
            if from != Some(*have) {
                return Err(HubError::invalid(format!(
                    "{location}: the server resumed at another byte ({from:?}, asked {have}); remove {} and run again",
                    part.display()
                )));
            }
            true
        }
        200 => false,
        // Nothing past the part's end: it is whole already (its checksum decides).
        416 if *have > 0 => return Ok((0, None)),
        _ => return Err(HubError::invalid(format!("{location}: the server answered {status}; try again later"))),
    };
    let mut hash = Sha256::new();
    if append {
        hash_file_into(part, &mut hash)?;
    } else {
        *have = 0;
    }
    let mut file =
        std::fs::OpenOptions::new().create(true).write(true).append(append).truncate(!append).open(part).map_err(
            |e| HubError::file(part, format!("cannot write ({e}); check the cache folder's space and rights")),
        )?;
    let length =
        resp.headers().get("content-length").and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse::<u64>().ok());
    let total = total.or(length.map(|n| n + *have));
    let mut body = resp.body_mut().as_reader();
    let mut buf = vec![0u8; 1 << 16];
    let mut fetched = 0u64;
    progress(Progress { done: *have, total });
    loop {
        let n = match body.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) => {
                let _ = file.flush();
                return Err(HubError::invalid(format!(
                    "{location}: the download was cut at {} bytes ({e}); run the command again to resume",
                    *have
                )));
            }
        };
        if max_bytes.is_some_and(|m| *have + n as u64 > m) {
            drop(file);
            let _ = std::fs::remove_file(part);
            return Err(HubError::invalid(format!(
                "{location}: the body runs past the {} bytes this file can have; nothing was kept. Check $DENS3R_HUB_ENDPOINT",
                max_bytes.unwrap_or(0)
            )));
        }
        file.write_all(&buf[..n])
            .map_err(|e| HubError::file(part, format!("cannot write ({e}); check the cache folder's space")))?;
        hash.update(&buf[..n]);
        *have += n as u64;
        fetched += n as u64;
        progress(Progress { done: *have, total });
    }
    file.flush().map_err(|e| HubError::file(part, format!("cannot write ({e})")))?;
    if let Some(t) = total {
        if *have != t {
            return Err(HubError::invalid(format!(
                "{location}: the download stopped at {} of {t} bytes; run the command again to resume",
                *have
            )));
        }
    }
    Ok((fetched, Some(hash)))
}

/// Free bytes on the disk holding `dir` (`None` where it cannot be told).
fn free_bytes(dir: &Path) -> Option<u64> {
    #[cfg(unix)]
    {
        use std::os::unix::ffi::OsStrExt;
        let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
        let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
        // SAFETY: `c` is a valid NUL-terminated path and `st` a writable statvfs.
        let r = unsafe { libc::statvfs(c.as_ptr(), &mut st) };
        (r == 0).then(|| st.f_bavail as u64 * st.f_frsize as u64)
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        None
    }
}

/// Whether a hub model file's bytes are what its name says: `model.safetensors` a complete
/// safetensors file (a header of JSON whose tensors' byte ranges lie in the file and fill it),
/// `config.json` a JSON object. Returns what was found instead.
pub fn check_hub_file(name: &str, path: &Path) -> Result<(), String> {
    let len = std::fs::metadata(path).map_err(|e| format!("an unreadable file ({e})"))?.len();
    let mut f = std::fs::File::open(path).map_err(|e| format!("an unreadable file ({e})"))?;
    let mut start = [0u8; 16];
    let got = f.read(&mut start).unwrap_or(0);
    let looks = || {
        let t = String::from_utf8_lossy(&start[..got]).to_ascii_lowercase();
        if t.trim_start().starts_with('<') {
            "an HTML or XML page".to_string()
        } else if start[..got].iter().all(|&b| b == 0) {
            format!("{len} bytes of zeros")
        } else {
            format!("{len} bytes that are not one")
        }
    };
    match name {
        "model.safetensors" => {
            if len < 10 {
                return Err(format!("{len} bytes (too short for a safetensors file)"));
            }
            let n = u64::from_le_bytes(start[..8].try_into().expect("8 bytes"));
            if n < 2 || n > (len - 8).min(100 << 20) {
                return Err(format!("{} (no safetensors header)", looks()));
            }
            let mut header = vec![0u8; n as usize];
            use std::io::Seek;
            f.seek(std::io::SeekFrom::Start(8)).map_err(|e| format!("an unreadable file ({e})"))?;
            f.read_exact(&mut header).map_err(|e| format!("an unreadable file ({e})"))?;
            let json: serde_json::Value = serde_json::from_slice(&header)
                .map_err(|_| format!("{} (its safetensors header is not JSON)", looks()))?;
            let obj = json.as_object().ok_or("a safetensors file whose header is not a JSON object")?;
            let body = len - 8 - n;
            let mut end = 0u64;
            for (k, v) in obj.iter().filter(|(k, _)| k.as_str() != "__metadata__") {
                let off = v.get("data_offsets").and_then(|o| o.as_array()).filter(|o| o.len() == 2);
                let pair = off.and_then(|o| Some((o[0].as_u64()?, o[1].as_u64()?)));
                match pair {
                    Some((a, b)) if a <= b && b <= body => end = end.max(b),
                    _ => {
                        return Err(format!(
                            "a safetensors file cut short or damaged (tensor {k} lies outside its {body} data bytes)"
                        ))
                    }
                }
            }
            if end != body {
                return Err(format!("a safetensors file whose tensors fill {end} of its {body} data bytes (damaged)"));
            }
            Ok(())
        }
        "config.json" => {
            let text = std::fs::read(path).map_err(|e| format!("an unreadable file ({e})"))?;
            match serde_json::from_slice::<serde_json::Value>(&text) {
                Ok(v) if v.is_object() => Ok(()),
                _ => Err(format!("{} (config.json is not a JSON object)", looks())),
            }
        }
        _ => Ok(()),
    }
}
