//! Bundles the viewer's script (three.js and the page's code, built by esbuild from `web/` by
//! `scripts/build-viewer.sh`) into the binary. Without it the crate still builds: the page then
//! shows its pictures and summary and says in one line how to get the 3-D view.

use std::path::PathBuf;

fn main() {
    let dir = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    let bundle = dir.join("web/dist/app.js");
    let licence = dir.join("web/node_modules/three/LICENSE");
    println!("cargo:rerun-if-changed={}", bundle.display());
    println!("cargo:rerun-if-changed={}", licence.display());
    let (app, bundled) = match std::fs::read_to_string(&bundle) {
        Ok(s) => (s, true),
        Err(_) => {
            println!(
                "cargo:warning=the 3-D viewer is not bundled ({} missing): run scripts/build-viewer.sh (needs npm), then rebuild",
                bundle.display()
            );
            (PLACEHOLDER.to_string(), false)
        }
    };
    let licence = std::fs::read_to_string(&licence)
        .unwrap_or_else(|_| "three.js: MIT licence, https://github.com/mrdoob/three.js/blob/dev/LICENSE\n".into());
    std::fs::write(out.join("app.js"), app).expect("OUT_DIR is writable");
    std::fs::write(out.join("THREE-LICENSE.txt"), licence).expect("OUT_DIR is writable");
    std::fs::write(
        out.join("bundled.rs"),
        format!("/// Whether this build carries the 3-D viewer.\npub const BUNDLED: bool = {bundled};\n"),
    )
    .expect("OUT_DIR is writable");
}

/// What a build without the bundle writes as viewer/app.js.
const PLACEHOLDER: &str = r#"window.addEventListener('DOMContentLoaded', () => {
  document.getElementById('status').textContent =
    'This dens3r was built without its 3-D viewer: run scripts/build-viewer.sh (needs npm), then rebuild.';
});
"#;
