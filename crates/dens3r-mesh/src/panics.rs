//! Running third-party parsing code that may panic on damaged input, as a refusal.

use std::cell::Cell;
use std::panic::{catch_unwind, AssertUnwindSafe};

thread_local! {
    static QUIET: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f`; a panic inside it gives `None` and prints nothing (the process's panic hook is
/// wrapped once so that it stays silent for a thread inside this call, and only for it).
pub fn catch_quietly<T>(f: impl FnOnce() -> T) -> Option<T> {
    static WRAP: std::sync::Once = std::sync::Once::new();
    WRAP.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(Cell::get) {
                previous(info);
            }
        }));
    });
    let was = QUIET.with(|q| q.replace(true));
    let out = catch_unwind(AssertUnwindSafe(f));
    QUIET.with(|q| q.set(was));
    out.ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_is_none_and_a_value_passes() {
        assert_eq!(catch_quietly(|| 7), Some(7));
        let v: Vec<u8> = Vec::new();
        assert_eq!(catch_quietly(|| v[3]), None);
        // The thread is loud again afterwards (the flag is restored).
        assert!(!QUIET.with(Cell::get));
    }
}
