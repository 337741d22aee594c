//! Downloads against a local hub: a checkpoint cut halfway resumes from where it stopped and
//! checks out; damaged bytes are refused and removed; a known name lands in the cache folder.

#[path = "../../../tests/support/http_server.rs"]
mod http_server;

use dens3r_hub::download::{download, part_path};
use std::path::Path;
use std::sync::atomic::Ordering;

fn fixture_checkpoint() -> Vec<u8> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fixtures/parity/A_shared_dec_48x64/weights.safetensors");
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// One test: the server and the environment variables are shared by everything in it.
#[test]
fn cut_downloads_resume_damaged_ones_are_refused_and_names_resolve() {
    let weights = fixture_checkpoint();
    let truth = http_server::sha256_hex(&weights);
    let (addr, hub) = http_server::start();
    hub.files.lock().unwrap().insert("model.safetensors".into(), weights.clone());
    hub.files.lock().unwrap().insert("config.json".into(), br#"{"enc_num_heads": 2, "dec_num_heads": 2}"#.to_vec());
    let dir = tempfile::tempdir().unwrap();
    let url = format!("{addr}/naver/m/resolve/main/model.safetensors");

    // Cut halfway: an error that says to run again, the half kept beside the target, no target.
    let dest = dir.path().join("model.safetensors");
    hub.cut.store(1, Ordering::SeqCst);
    let e = download(&url, &dest, None, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("run the command again to resume"), "{e}");
    let half = std::fs::metadata(part_path(&dest)).unwrap().len();
    assert_eq!(half, weights.len() as u64 / 2);
    assert!(!dest.exists());

    // Run again: it asks for the rest only, and the file equals the original.
    hub.log.lock().unwrap().clear();
    let mut seen = Vec::new();
    let got = download(&url, &dest, None, &mut |p| seen.push(p)).unwrap();
    assert_eq!((got.resumed_from, got.fetched), (half, weights.len() as u64 - half));
    assert_eq!(got.sha256, truth);
    assert_eq!(got.checked_against, "server");
    assert_eq!(std::fs::read(&dest).unwrap(), weights);
    assert!(!part_path(&dest).exists());
    let log = hub.log.lock().unwrap().clone();
    assert!(log.contains(&format!("GET /cdn/model.safetensors {half}-")), "{log:?}");
    assert_eq!(seen.last().map(|p| (p.done, p.total)), Some((weights.len() as u64, Some(weights.len() as u64))));
    assert!(seen.windows(2).all(|w| w[0].done <= w[1].done));

    // Damaged bytes under the true checksum: refused, nothing left behind.
    let bad = dir.path().join("bad.safetensors");
    hub.corrupt.store(true, Ordering::SeqCst);
    let e = download(&url, &bad, None, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("does not match its SHA-256") && e.contains(&truth), "{e}");
    assert!(!bad.exists() && !part_path(&bad).exists());
    // A catalogue checksum wins over the server's: the true bytes against a wrong one fail.
    hub.corrupt.store(false, Ordering::SeqCst);
    let e = download(&url, &bad, Some(&"0".repeat(64)), &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("catalogue"), "{e}");
    assert!(!bad.exists());

    // A known name: its files land in $DENS3R_HOME/models/NAME from $DENS3R_HUB_ENDPOINT.
    let home = tempfile::tempdir().unwrap();
    std::env::set_var(dens3r_hub::HOME_ENV, home.path());
    std::env::set_var(dens3r_hub::ENDPOINT_ENV, format!("{addr}/"));
    let k = dens3r_hub::find("dust3r-512-dpt").unwrap();
    assert!(!dens3r_hub::is_cached(k));
    let folder = dens3r_hub::fetch_model(k, &mut |_, _| {}).unwrap();
    assert_eq!(folder, home.path().join("models").join("dust3r-512-dpt"));
    assert_eq!(std::fs::read(folder.join("model.safetensors")).unwrap(), weights);
    assert!(dens3r_hub::is_cached(k));
    let record = std::fs::read_to_string(folder.join("model.safetensors.sha256")).unwrap();
    assert!(record.starts_with(&truth) && record.contains("server"), "{record}");
    // Cached: a second call fetches nothing.
    hub.log.lock().unwrap().clear();
    dens3r_hub::fetch_model(k, &mut |_, _| {}).unwrap();
    assert!(hub.log.lock().unwrap().is_empty());
    // A manual entry says where to get it; an unreachable hub says to check the address.
    let e = dens3r_hub::fetch_model(dens3r_hub::find("dens3r-unify").unwrap(), &mut |_, _| {}).unwrap_err();
    assert!(e.to_string().contains("Taobao3D"), "{e}");
    std::env::set_var(dens3r_hub::ENDPOINT_ENV, "http://127.0.0.1:9");
    let e = dens3r_hub::fetch_model(dens3r_hub::find("mast3r-512-metric").unwrap(), &mut |_, _| {}).unwrap_err();
    assert!(e.to_string().contains("DENS3R_HUB_ENDPOINT"), "{e}");
    // Issue 77, 10: a refused download left an empty model folder behind.
    assert!(!dens3r_hub::model_dir(dens3r_hub::find("mast3r-512-metric").unwrap()).exists());

    // Issue 66, 3: poisoned downloads. A hub answering an HTML page (200, no checksum) for
    // every file: refused, nothing cached, and a later good hub downloads the real files.
    std::env::set_var(dens3r_hub::ENDPOINT_ENV, &addr);
    let k = dens3r_hub::find("dust3r-512-linear").unwrap();
    let folder = dens3r_hub::model_dir(k);
    hub.html.store(true, Ordering::SeqCst);
    let e = dens3r_hub::fetch_model(k, &mut |_, _| {}).unwrap_err().to_string();
    assert!(e.contains("model.safetensors") && e.contains("HTML") && !e.contains('\n'), "{e}");
    assert!(!folder.join("model.safetensors").exists() && !part_path(&folder.join("model.safetensors")).exists());
    assert!(!dens3r_hub::is_cached(k));
    assert!(!folder.exists(), "an empty model folder was left");
    // A body with no length announced that stops halfway: refused, not installed.
    hub.html.store(false, Ordering::SeqCst);
    hub.unsized_cut.store(true, Ordering::SeqCst);
    let e = dens3r_hub::fetch_model(k, &mut |_, _| {}).unwrap_err().to_string();
    assert!(e.contains("cut short") && e.contains("model.safetensors"), "{e}");
    assert!(!folder.join("model.safetensors").exists() && !dens3r_hub::is_cached(k));
    hub.unsized_cut.store(false, Ordering::SeqCst);
    // A size announced beyond the catalogue's: refused before a byte is fetched.
    let big = dir.path().join("big.safetensors");
    let expect = dens3r_hub::download::Expect { max_bytes: Some(1000), ..Default::default() };
    hub.log.lock().unwrap().clear();
    let e = dens3r_hub::download::download_checked(&url, &big, &expect, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("more than the 1000"), "{e}");
    assert!(!hub.log.lock().unwrap().iter().any(|l| l.starts_with("GET")), "fetched anyway");
    // An older dens3r's poisoned cache entry (an HTML page with its download record) is not
    // "cached" and is fetched again; a damaged file placed by hand is named and left alone.
    std::fs::create_dir_all(&folder).unwrap();
    std::fs::write(folder.join("model.safetensors"), b"<!DOCTYPE html><html>502</html>").unwrap();
    std::fs::write(folder.join("model.safetensors.sha256"), "00  none  x\n").unwrap();
    std::fs::write(folder.join("config.json"), br#"{"enc_num_heads": 2, "dec_num_heads": 2}"#).unwrap();
    assert!(!dens3r_hub::is_cached(k));
    let e = dens3r_hub::verify_cached(k, "model.safetensors").unwrap_err().to_string();
    assert!(e.contains("HTML"), "{e}");
    dens3r_hub::fetch_model(k, &mut |_, _| {}).unwrap();
    assert_eq!(std::fs::read(folder.join("model.safetensors")).unwrap(), weights);
    assert!(dens3r_hub::is_cached(k));
    assert!(dens3r_hub::verify_cached(k, "model.safetensors").unwrap().contains("matches"));
    std::fs::write(folder.join("model.safetensors"), [0u8; 64]).unwrap();
    std::fs::remove_file(folder.join("model.safetensors.sha256")).unwrap();
    let e = dens3r_hub::fetch_model(k, &mut |_, _| {}).unwrap_err().to_string();
    assert!(e.contains("zeros") && e.contains("remove it"), "{e}");
    assert_eq!(std::fs::read(folder.join("model.safetensors")).unwrap(), [0u8; 64]);
}
