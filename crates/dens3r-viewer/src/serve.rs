//! `dens3r view OUT`: the folder served on 127.0.0.1, read-only, for browsers that refuse a
//! page opened from the file system.
//!
//! Only files under the folder are served: a request's path is resolved with its symbolic
//! links and must stay under the folder's own resolved path (`rootfs -> /` serves nothing).
//! Only requests naming this machine in their `Host` header are answered (`127.0.0.1`,
//! `localhost` or `[::1]`, with the server's port or none), so a web page whose name was made
//! to resolve to 127.0.0.1 (DNS rebinding) cannot read the folder. Each connection has a
//! thread of its own, at most [`MAX_CLIENTS`] at once, with read and write timeouts: a client
//! that stalls holds only its own thread, for at most [`TIMEOUT`].
//!
//! Hand-written on `std::net` rather than `tiny_http` (which the first version used): that
//! crate gives no access to its sockets' timeouts and answers one request after another, so
//! one client that stopped reading held every other.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Connections answered at once; more wait in the listen queue rather than being refused.
pub const MAX_CLIENTS: usize = 32;
/// How long a client may take to send its request, or to take each piece of the answer.
pub const TIMEOUT: Duration = Duration::from_secs(10);
/// The longest request head read (request line and headers).
const MAX_HEAD: usize = 16 * 1024;

/// A running server.
pub struct Server {
    listener: TcpListener,
    root: PathBuf,
    port: u16,
}

impl Server {
    /// Binds `127.0.0.1:port` (0: any free port) to serve `root`.
    pub fn bind(root: &Path, port: u16) -> Result<Server, String> {
        let root = root.canonicalize().map_err(|e| format!("{}: {e}", root.display()))?;
        let listener = TcpListener::bind(("127.0.0.1", port))
            .map_err(|e| format!("127.0.0.1:{port}: {e}; pick another with --port"))?;
        let port = listener.local_addr().map_err(|e| e.to_string())?.port();
        Ok(Server { listener, root, port })
    }

    /// The address to open.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}/", self.port)
    }

    /// Answers requests until the process ends, each connection on a thread of its own.
    pub fn run(&self) {
        let active = Arc::new(AtomicUsize::new(0));
        for stream in self.listener.incoming() {
            let Ok(stream) = stream else { continue };
            // Wait for a free place rather than refuse: a page loads a few files at once.
            while active.load(Ordering::SeqCst) >= MAX_CLIENTS {
                std::thread::sleep(Duration::from_millis(10));
            }
            active.fetch_add(1, Ordering::SeqCst);
            let (root, port, mine) = (self.root.clone(), self.port, Arc::clone(&active));
            let spawned = std::thread::Builder::new().name("view-client".into()).spawn(move || {
                let _ = answer(stream, &root, port);
                mine.fetch_sub(1, Ordering::SeqCst);
            });
            if spawned.is_err() {
                active.fetch_sub(1, Ordering::SeqCst);
            }
        }
    }
}

/// A file under `root` for a request path; `..` and absolute parts, missing files and paths
/// whose symbolic links lead out of `root` give None.
pub fn resolve(root: &Path, url: &str) -> Option<PathBuf> {
    let path = url.split(['?', '#']).next().unwrap_or("");
    let path = percent_decode(path)?;
    let rel = Path::new(path.trim_start_matches('/'));
    if rel.components().any(|c| !matches!(c, Component::Normal(_))) {
        return None;
    }
    let full = root.join(rel);
    let full = if full.is_dir() { full.join("index.html") } else { full };
    let (real_root, real) = (root.canonicalize().ok()?, full.canonicalize().ok()?);
    (real.starts_with(&real_root) && real.is_file()).then_some(full)
}

/// Whether a `Host` header names this machine (with `port`, or no port).
pub fn local_host(host: &str, port: u16) -> bool {
    let host = host.trim().to_ascii_lowercase();
    let (name, p) = match host.rsplit_once(':') {
        Some((n, p)) if !n.is_empty() && !p.contains(']') => (n.to_string(), Some(p.to_string())),
        _ => (host.clone(), None),
    };
    ["127.0.0.1", "localhost", "[::1]"].contains(&name.as_str()) && p.is_none_or(|p| p == port.to_string())
}

fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).unwrap_or("") {
        "html" => "text/html; charset=utf-8",
        "js" => "text/javascript; charset=utf-8",
        "json" => "application/json",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "glb" => "model/gltf-binary",
        "txt" | "md" => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

/// Reads one request from `stream` and answers it; the connection then closes.
fn answer(stream: TcpStream, root: &Path, port: u16) -> std::io::Result<()> {
    stream.set_read_timeout(Some(TIMEOUT))?;
    stream.set_write_timeout(Some(TIMEOUT))?;
    let mut reader = BufReader::new(stream.try_clone()?.take(MAX_HEAD as u64));
    let mut lines = Vec::new();
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 {
            return Ok(()); // closed, or the head is too long
        }
        let line = line.trim_end().to_string();
        if line.is_empty() {
            break;
        }
        lines.push(line);
    }
    let mut out = stream;
    let mut words = lines.first().map(|l| l.split_whitespace()).into_iter().flatten();
    let (method, target) = (words.next().unwrap_or(""), words.next().unwrap_or(""));
    let host = lines.iter().skip(1).find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.trim().eq_ignore_ascii_case("host").then(|| v.trim().to_string())
    });
    if !host.as_deref().is_some_and(|h| local_host(h, port)) {
        return plain(
            &mut out,
            "421 Misdirected Request",
            "this server answers only requests for 127.0.0.1 or localhost",
        );
    }
    if method != "GET" && method != "HEAD" {
        return plain(&mut out, "405 Method Not Allowed", "only GET and HEAD");
    }
    let Some(path) = resolve(root, target) else { return plain(&mut out, "404 Not Found", "not found") };
    let Ok(mut file) = std::fs::File::open(&path) else { return plain(&mut out, "404 Not Found", "not found") };
    let len = file.metadata()?.len();
    write!(
        out,
        "HTTP/1.1 200 OK\r\nContent-Type: {}\r\nContent-Length: {len}\r\nConnection: close\r\n\r\n",
        content_type(&path)
    )?;
    if method == "GET" {
        std::io::copy(&mut file, &mut out)?;
    }
    out.flush()
}

fn plain(out: &mut TcpStream, status: &str, body: &str) -> std::io::Result<()> {
    write!(
        out,
        "HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    out.flush()
}
