//! `dens3r view OUT`: the folder served on 127.0.0.1, read-only, for browsers that refuse a
//! page opened from the file system.

use std::path::{Component, Path, PathBuf};

/// A running server.
pub struct Server {
    inner: tiny_http::Server,
    root: PathBuf,
}

impl Server {
    /// Binds `127.0.0.1:port` (0: any free port) to serve `root`.
    pub fn bind(root: &Path, port: u16) -> Result<Server, String> {
        let inner = tiny_http::Server::http(("127.0.0.1", port))
            .map_err(|e| format!("127.0.0.1:{port}: {e}; pick another with --port"))?;
        Ok(Server { inner, root: root.to_path_buf() })
    }

    /// The address to open.
    pub fn url(&self) -> String {
        match self.inner.server_addr().to_ip() {
            Some(a) => format!("http://{a}/"),
            None => "http://127.0.0.1/".into(),
        }
    }

    /// Answers requests until the process ends.
    pub fn run(&self) {
        for req in self.inner.incoming_requests() {
            let resp = respond(&self.root, req.url());
            let _ = req.respond(resp);
        }
    }
}

/// A file under `root` for a request path; `..` and absolute parts are refused.
pub fn resolve(root: &Path, url: &str) -> Option<PathBuf> {
    let path = url.split(['?', '#']).next().unwrap_or("");
    let path = percent_decode(path)?;
    let rel = Path::new(path.trim_start_matches('/'));
    if rel.components().any(|c| !matches!(c, Component::Normal(_))) {
        return None;
    }
    let full = root.join(rel);
    Some(if full.is_dir() { full.join("index.html") } else { full })
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

fn respond(root: &Path, url: &str) -> tiny_http::Response<Box<dyn std::io::Read + Send>> {
    let not_found = || tiny_http::Response::from_string("not found").with_status_code(404).boxed();
    let Some(path) = resolve(root, url) else { return not_found() };
    match std::fs::File::open(&path) {
        Ok(f) if path.is_file() => {
            let header = tiny_http::Header::from_bytes(&b"Content-Type"[..], content_type(&path).as_bytes())
                .expect("a valid header");
            tiny_http::Response::from_file(f).with_header(header).boxed()
        }
        _ => not_found(),
    }
}
