//! Running third-party parsing code that may panic on damaged input, as a refusal.

use std::cell::Cell;
use std::panic::{catch_unwind, AssertUnwindSafe};

thread_local! {
    static QUIET: Cell<bool> = const { Cell::new(false) };
}

/// A panic caught by [`catch_quietly`]: the first line of its message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct Panicked(pub String);

/// Runs `f`; a panic inside it gives `Err` with the first line of its message and prints
/// nothing (the process's panic hook is wrapped once so that it stays silent for a thread
/// inside this call, and only for it).
pub fn catch_quietly<T>(f: impl FnOnce() -> T) -> Result<T, Panicked> {
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
    out.map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .map(|s| s.lines().next().unwrap_or("").to_string())
            .unwrap_or_else(|| "a panic without a message".into())
    })
    .map_err(Panicked)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_is_its_message_and_a_value_passes() {
        assert_eq!(catch_quietly(|| 7), Ok(7));
        let v: Vec<u8> = Vec::new();
        let e = catch_quietly(|| v[3]).unwrap_err().0;
        assert!(e.contains("index out of bounds"), "{e}");
        // The thread is loud again afterwards (the flag is restored).
        assert!(!QUIET.with(Cell::get));
    }
}
