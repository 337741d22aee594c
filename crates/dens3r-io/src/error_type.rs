//! The error type of a library whose failures either name a file or a setting: defined once,
//! instantiated per crate (each crate's type is its own, so it can convert its neighbours'
//! errors).

/// Defines `pub enum $name { File { path, message }, Invalid(String) }` with one-line messages
/// (`PATH: message`, or the message), `file` / `invalid` constructors, `From` for the listed
/// errors that name a file (their `path` and `message` fields are kept) and for the listed plain
/// errors (kept as their message). The calling crate depends on `thiserror`.
#[macro_export]
macro_rules! file_or_setting_error {
    ($(#[$doc:meta])* $name:ident; files: [$($f:ty),* $(,)?]; plain: [$($p:ty),* $(,)?] $(;)?) => {
        $(#[$doc])*
        #[derive(Debug, thiserror::Error)]
        pub enum $name {
            /// A file or folder could not be used (read, decoded, written, or it does not fit).
            #[error("{}: {message}", path.display())]
            File {
                /// The file or folder at fault.
                path: std::path::PathBuf,
                /// What is wrong with it and how to fix it.
                message: String,
            },
            /// A setting, data set or state that cannot work, and the fix.
            #[error("{0}")]
            Invalid(String),
        }

        impl $name {
            /// A problem with the file or folder `path`.
            pub fn file(path: &std::path::Path, message: impl Into<String>) -> Self {
                Self::File { path: path.to_path_buf(), message: message.into() }
            }

            /// A setting or state that cannot work.
            pub fn invalid(message: impl Into<String>) -> Self {
                Self::Invalid(message.into())
            }
        }

        $(impl From<$f> for $name {
            fn from(e: $f) -> Self {
                Self::File { path: e.path, message: e.message }
            }
        })*

        $(impl From<$p> for $name {
            fn from(e: $p) -> Self {
                Self::Invalid(e.to_string())
            }
        })*
    };
}

/// Defines `pub struct $name { path, message }`, an error about one file displayed as one line
/// (`PATH: message`), with a `new(path, message)` constructor and `From` for the listed errors
/// of the same shape (their `path` and `message` are kept). The calling crate depends on
/// `thiserror`.
#[macro_export]
macro_rules! file_error {
    ($(#[$doc:meta])* $name:ident; from: [$($f:ty),* $(,)?] $(;)?) => {
        $(#[$doc])*
        #[derive(Debug, thiserror::Error)]
        #[error("{}: {message}", path.display())]
        pub struct $name {
            /// The file or folder at fault.
            pub path: std::path::PathBuf,
            /// What is wrong with it and how to fix it.
            pub message: String,
        }

        impl $name {
            /// A problem with the file or folder `path`.
            pub fn new(path: &std::path::Path, message: impl Into<String>) -> Self {
                Self { path: path.to_path_buf(), message: message.into() }
            }
        }

        $(impl From<$f> for $name {
            fn from(e: $f) -> Self {
                Self { path: e.path, message: e.message }
            }
        })*
    };
}
