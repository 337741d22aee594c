//! A small HTTP/1.1 file server on 127.0.0.1 for download tests, shaped like the Hugging Face
//! hub: `/{repo}/resolve/main/{file}` answers 302 to `/cdn/{file}` with the file's SHA-256 in
//! `X-Linked-Etag` and its size in `X-Linked-Size`; `/cdn/{file}` serves the bytes with `Range`
//! support. It can cut a body halfway (the socket closed after half the bytes) or serve
//! damaged bytes under the true checksum.

#![allow(dead_code)]

use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// The server's state, shared with the test.
#[derive(Default)]
pub struct Hub {
    /// Files by name.
    pub files: Mutex<BTreeMap<String, Vec<u8>>>,
    /// How many more body responses to cut halfway.
    pub cut: AtomicUsize,
    /// Serve every body with its first byte flipped (the headers keep the true SHA-256).
    pub corrupt: AtomicBool,
    /// Every request as `METHOD PATH [RANGE]`.
    pub log: Mutex<Vec<String>>,
    /// Answer every file address with 200 and an HTML error page, no checksum (a misconfigured
    /// mirror or a captive portal).
    pub html: AtomicBool,
    /// Serve bodies with no Content-Length, closing the connection after half of them.
    pub unsized_cut: AtomicBool,
}

/// SHA-256 in hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// Starts the server on a free port; returns its address (`http://127.0.0.1:PORT`) and state.
/// It runs until the test process ends.
pub fn start() -> (String, Arc<Hub>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("a free port");
    let addr = format!("http://{}", listener.local_addr().unwrap());
    let hub = Arc::new(Hub::default());
    let h = hub.clone();
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let h = h.clone();
            std::thread::spawn(move || {
                let _ = serve(stream, &h);
            });
        }
    });
    (addr, hub)
}

fn serve(mut stream: TcpStream, hub: &Hub) -> std::io::Result<()> {
    let mut reader = BufReader::new(stream.try_clone()?);
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 {
            return Ok(());
        }
        let mut parts = line.split_whitespace();
        let (method, path) = (parts.next().unwrap_or("").to_string(), parts.next().unwrap_or("").to_string());
        let mut range = None;
        loop {
            let mut h = String::new();
            if reader.read_line(&mut h)? == 0 || h.trim().is_empty() {
                break;
            }
            if let Some((k, v)) = h.split_once(':') {
                if k.trim().eq_ignore_ascii_case("range") {
                    range = v.trim().strip_prefix("bytes=").and_then(|r| r.trim_end_matches('-').parse::<usize>().ok());
                }
            }
        }
        hub.log.lock().unwrap().push(format!("{method} {path}{}", range.map(|r| format!(" {r}-")).unwrap_or_default()));
        let files = hub.files.lock().unwrap().clone();
        if hub.html.load(Ordering::SeqCst) {
            let page = b"<!DOCTYPE html><html><body>502 Bad Gateway</body></html>";
            let headers = [("Content-Length".to_string(), page.len().to_string())];
            let body: &[u8] = if method == "HEAD" { b"" } else { page };
            respond(&mut stream, "200 OK", &headers, body)?;
            continue;
        }
        if let Some((_, file)) = path.split_once("/resolve/main/") {
            let Some(data) = files.get(file) else { return respond(&mut stream, "404 Not Found", &[], b"") };
            let mut headers = vec![
                ("Location".to_string(), format!("/cdn/{file}")),
                ("X-Linked-Etag".to_string(), format!("\"{}\"", sha256_hex(data))),
                ("X-Linked-Size".to_string(), data.len().to_string()),
            ];
            if hub.unsized_cut.load(Ordering::SeqCst) {
                headers.truncate(1);
            }
            respond(&mut stream, "302 Found", &headers, b"")?;
            continue;
        }
        let Some(data) = path.strip_prefix("/cdn/").and_then(|f| files.get(f)) else {
            return respond(&mut stream, "404 Not Found", &[], b"");
        };
        let mut body = data.clone();
        if hub.corrupt.load(Ordering::SeqCst) {
            body[0] ^= 0xFF;
        }
        let from = range.unwrap_or(0).min(body.len());
        let (status, mut headers) = if range.is_some() {
            (
                "206 Partial Content",
                vec![("Content-Range".into(), format!("bytes {from}-{}/{}", body.len() - 1, body.len()))],
            )
        } else {
            ("200 OK", vec![])
        };
        let slice = &body[from..];
        headers.push(("Content-Length".into(), slice.len().to_string()));
        if method == "HEAD" {
            respond(&mut stream, status, &headers, b"")?;
            continue;
        }
        if hub.unsized_cut.load(Ordering::SeqCst) {
            stream.write_all(format!("HTTP/1.1 {status}\r\nConnection: close\r\n\r\n").as_bytes())?;
            if method != "HEAD" {
                stream.write_all(&slice[..slice.len() / 2])?;
            }
            stream.flush()?;
            return stream.shutdown(std::net::Shutdown::Both);
        }
        let cut = hub.cut.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |c| c.checked_sub(1)).is_ok();
        if cut {
            // Headers promise the whole rest; half of it arrives, then the connection drops.
            write_head(&mut stream, status, &headers)?;
            stream.write_all(&slice[..slice.len() / 2])?;
            stream.flush()?;
            return stream.shutdown(std::net::Shutdown::Both);
        }
        respond(&mut stream, status, &headers, slice)?;
    }
}

fn write_head(stream: &mut TcpStream, status: &str, headers: &[(String, String)]) -> std::io::Result<()> {
    let mut head = format!("HTTP/1.1 {status}\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    if !headers.iter().any(|(k, _)| k == "Content-Length") {
        head.push_str("Content-Length: 0\r\n");
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())
}

fn respond(stream: &mut TcpStream, status: &str, headers: &[(String, String)], body: &[u8]) -> std::io::Result<()> {
    write_head(stream, status, headers)?;
    stream.write_all(body)?;
    stream.flush()
}
