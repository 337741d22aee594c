//! `classes.json`: class id -> name, `{"1": "wall", ...}` (scene folders, label folders, head
//! outputs).

use crate::error::SceneError;
use dens3r_io::write_atomic;
use std::collections::BTreeMap;
use std::path::Path;

/// Reads a `classes.json` file.
pub fn read_classes(path: &Path) -> Result<BTreeMap<u16, String>, SceneError> {
    let text = std::fs::read_to_string(path).map_err(|e| SceneError::new(path, format!("cannot read: {e}")))?;
    let raw: BTreeMap<String, String> = serde_json::from_str(&text)
        .map_err(|e| SceneError::new(path, format!("must map ids to names, {{\"1\": \"wall\"}}: {e}")))?;
    raw.into_iter()
        .map(|(k, v)| {
            k.parse::<u16>()
                .map(|k| (k, v))
                .map_err(|_| SceneError::new(path, format!("key '{k}' is not a class id (0..65535)")))
        })
        .collect()
}

/// Writes a `classes.json` file atomically.
pub fn write_classes(path: &Path, classes: &BTreeMap<u16, String>) -> Result<(), SceneError> {
    let map: BTreeMap<String, &String> = classes.iter().map(|(k, v)| (k.to_string(), v)).collect();
    let text = serde_json::to_string_pretty(&map).expect("string map serialises");
    write_atomic(path, |w| std::io::Write::write_all(w, text.as_bytes()))?;
    Ok(())
}
