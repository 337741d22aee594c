//! Bounded, seeded mutation of every reader of outside data (`readers::targets`): each seed is
//! read cleanly, then mutants of it (bit flips, interesting bytes and integers, truncation,
//! deleted / repeated / inserted spans, and for text, numbers replaced by huge, negative or
//! non-finite ones) must each be read or refused without a panic, and without allocating more
//! than the file could honestly need. `DENS3R_FUZZ_CASES` sets the mutants per reader
//! (default 2000); `DENS3R_FUZZ_SEED` the seed.

mod readers;

use rand::{Rng as _, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::panic::AssertUnwindSafe;
use std::path::Path;

/// Largest single allocation and live total a case may reach on its own thread: 256 MB plus
/// 64 bytes per byte of input (decompressed images and meshes legitimately grow).
fn budget(input: usize) -> usize {
    (256 << 20) + 64 * input
}

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
    static LIMIT: Cell<usize> = const { Cell::new(usize::MAX) };
    static TARGET: Cell<&'static str> = const { Cell::new("") };
}

/// Counts this thread's live bytes; a single request over the case's limit aborts with a
/// message (returning null would abort anyway, without one).
struct Counting;

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let _ = LIVE.try_with(|live| {
            let limit = LIMIT.try_with(Cell::get).unwrap_or(usize::MAX);
            if l.size() > limit {
                // Straight to stderr, without allocating (the harness's capture dies with us).
                use std::io::Write;
                let mut buf = [0u8; 160];
                let mut c = std::io::Cursor::new(&mut buf[..]);
                let name = TARGET.try_with(Cell::get).unwrap_or("?");
                let _ = writeln!(
                    c,
                    "fuzz_readers: {name}: one allocation of {} bytes, over the budget {limit} (input: target/tmp/fuzz-cases/{name})",
                    l.size()
                );
                let n = c.position() as usize;
                let _ = std::io::stderr().write_all(&buf[..n]);
                std::process::abort();
            }
            let now = live.get() + l.size();
            live.set(now);
            let _ = PEAK.try_with(|p| p.set(p.get().max(now)));
        });
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        let _ = LIVE.try_with(|live| live.set(live.get().saturating_sub(l.size())));
        // SAFETY: p came from System.alloc with layout l.
        unsafe { System.dealloc(p, l) }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// The seeded draws of the mutations.
struct Rng(ChaCha8Rng);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0.gen()
    }
    fn below(&mut self, n: usize) -> usize {
        self.0.gen_range(0..n.max(1))
    }
}

const BYTES: [u8; 8] = [0x00, 0xff, 0x7f, 0x80, 0x01, 0xfe, b'-', b'9'];
const INTS: [u64; 7] = [0, u64::MAX, 0x7fff_ffff, 0x8000_0000, 0xffff_ffff, 1 << 40, 0x7fff_ffff_ffff_ffff];
const TEXT: [&str; 9] = ["1000000000000", "-1", "nan", "1e40", "-0", "18446744073709551615", "4294967297", "0", "inf"];

/// One to four stacked mutations of `seed`.
fn mutate(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let n = b.len();
        match rng.below(8) {
            0 if n > 0 => {
                let i = rng.below(n);
                b[i] ^= 1 << rng.below(8);
            }
            1 if n > 0 => {
                let i = rng.below(n);
                b[i] = BYTES[rng.below(BYTES.len())];
            }
            2 if n >= 8 => {
                let i = rng.below(n - 7);
                let v = INTS[rng.below(INTS.len())].to_le_bytes();
                let w = [1, 2, 4, 8][rng.below(4)];
                b[i..i + w].copy_from_slice(&v[..w]);
            }
            3 => b.truncate(rng.below(n + 1)),
            4 if n > 0 => {
                let i = rng.below(n);
                let len = 1 + rng.below((n - i).min(64));
                b.drain(i..i + len);
            }
            5 if n > 0 => {
                let i = rng.below(n);
                let len = 1 + rng.below((n - i).min(64));
                let span = b[i..i + len].to_vec();
                let at = rng.below(n + 1);
                b.splice(at..at, span.iter().copied().cycle().take(len * (1 + rng.below(4))));
            }
            6 => {
                let at = rng.below(n + 1);
                let junk: Vec<u8> = (0..1 + rng.below(16)).map(|_| rng.next() as u8).collect();
                b.splice(at..at, junk);
            }
            _ => {
                // A run of digits (text formats' counts, sizes and values) becomes another number.
                let digits: Vec<usize> = (0..n).filter(|&i| b[i].is_ascii_digit()).collect();
                if digits.is_empty() {
                    continue;
                }
                let mut i = digits[rng.below(digits.len())];
                let mut j = i;
                while i > 0 && b[i - 1].is_ascii_digit() {
                    i -= 1;
                }
                while j < n && (b[j].is_ascii_digit() || b[j] == b'.') {
                    j += 1;
                }
                b.splice(i..j, TEXT[rng.below(TEXT.len())].bytes());
            }
        }
    }
    b
}

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// What a run over one reader found.
struct Report {
    cases: usize,
    refused: usize,
    panics: Vec<String>,
    peak: usize,
}

fn fuzz(t: &readers::Target, cases: usize, seed: u64) -> Report {
    // A fixed folder per reader, so the input of a case that aborts (an allocation over the
    // budget) is still there to look at.
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-cases").join(t.name);
    let _ = std::fs::remove_dir_all(&dir);
    TARGET.with(|n| n.set(t.name));
    let bytes = readers::prepare(t, &dir);
    if let Err(e) = readers::run(t, &dir, &bytes) {
        panic!("{}: the unmutated seed is refused: {e}", t.name);
    }
    let mut rng =
        Rng(ChaCha8Rng::seed_from_u64(seed ^ readers::targets().iter().position(|x| x.name == t.name).unwrap() as u64));
    let mut r = Report { cases, refused: 0, panics: Vec::new(), peak: 0 };
    for case in 0..cases {
        let m = mutate(&bytes, &mut rng);
        LIMIT.with(|l| l.set(budget(m.len().max(bytes.len()))));
        PEAK.with(|p| p.set(LIVE.with(Cell::get)));
        let base = LIVE.with(Cell::get);
        FUZZING.with(|f| f.set(true));
        let out = std::panic::catch_unwind(AssertUnwindSafe(|| readers::run(t, &dir, &m)));
        FUZZING.with(|f| f.set(false));
        LIMIT.with(|l| l.set(usize::MAX));
        let peak = PEAK.with(Cell::get).saturating_sub(base);
        r.peak = r.peak.max(peak);
        match out {
            Ok(Ok(())) => {}
            Ok(Err(_)) => r.refused += 1,
            Err(p) => {
                let msg = p
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                let kept = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-panics");
                let path = kept.join(format!("{}-{case}", t.name));
                let _ = std::fs::create_dir_all(&kept).and_then(|_| std::fs::write(&path, &m));
                let at = WHERE.with(|w| w.borrow().clone());
                r.panics.push(format!("case {case} ({} bytes, kept in {}): {msg} at {at}", m.len(), path.display()));
            }
        }
        if peak > budget(m.len().max(bytes.len())) {
            r.panics.push(format!("case {case}: {peak} live bytes, over the budget"));
        }
    }
    r
}

thread_local! {
    static FUZZING: Cell<bool> = const { Cell::new(false) };
    static WHERE: std::cell::RefCell<String> = const { std::cell::RefCell::new(String::new()) };
}

/// Panics of a thread that is fuzzing are caught and reported by [`fuzz`], so the hook stays
/// quiet for them (and only them: tests run in parallel).
fn quiet_while_fuzzing() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if FUZZING.with(Cell::get) {
                let at = info.location().map(|l| format!("{}:{}", l.file(), l.line())).unwrap_or_default();
                WHERE.with(|w| *w.borrow_mut() = at);
            } else {
                default(info);
            }
        }));
    });
}

fn check(name: &str) {
    let cases = env_usize("DENS3R_FUZZ_CASES", 2000);
    let seed = env_usize("DENS3R_FUZZ_SEED", 0x5eed) as u64;
    let targets = readers::targets();
    let t = targets.iter().find(|t| t.name == name).expect("a known target");
    quiet_while_fuzzing();
    let r = fuzz(t, cases, seed);
    println!(
        "{name}: {} mutants, {} refused cleanly, {} read, peak {:.1} MB, {} panics",
        r.cases,
        r.refused,
        r.cases - r.refused - r.panics.len(),
        r.peak as f64 / 1e6,
        r.panics.len()
    );
    assert!(r.panics.is_empty(), "{name}: {}", r.panics.join("\n"));
}

macro_rules! fuzz_tests {
    ($($f:ident => $name:literal),* $(,)?) => {
        $(#[test] fn $f() { check($name); })*

        #[test]
        fn every_target_has_a_test() {
            let tested = [$($name),*];
            for t in readers::targets() {
                assert!(tested.contains(&t.name), "target {} has no test", t.name);
            }
        }
    };
}

fuzz_tests! {
    npy => "npy",
    safetensors => "safetensors",
    model_json => "model-json",
    pth => "pth",
    pth_nesting => "pth-nesting",
    safetensors_offsets => "safetensors-offsets",
    onnx => "onnx",
    png => "png",
    jpeg => "jpeg",
    pnm => "pnm",
    label_png => "label-png",
    mesh_ply => "mesh-ply",
    mesh_ply_ascii => "mesh-ply-ascii",
    mesh_obj => "mesh-obj",
    mesh_off => "mesh-off",
    mesh_glb => "mesh-glb",
    cameras_json => "cameras-json",
    scene_depth => "scene-depth",
    scene_image => "scene-image",
    classes_json => "classes-json",
    head_json => "head-json",
    head_safetensors => "head-safetensors",
    pair_cache => "pair-cache",
    feature_cache => "feature-cache",
    arch_toml => "arch-toml",
    train_log => "train-log",
}
