//! One error type for the whole crate; the pyo3 layer maps each kind to one
//! Python exception class (see `python/can_bridge/_errors.py`).

use std::fmt;

/// What went wrong, by kind. Every variant carries a readable message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Error {
    /// A setting or channel string is invalid (maps to `ConfigError`, a `ValueError`).
    Config(String),
    /// A command was refused at `set_command` (maps to `CommandError`, a `ValueError`).
    Command(String),
    /// Opening, reading or writing the transport failed (maps to `TransportError`, an `OSError`).
    Transport(String),
    /// The call does not fit the bridge's life cycle, e.g. `start` twice (maps to `StateError`).
    State(String),
}

impl Error {
    /// A transport error built from the last OS error, with context.
    pub fn last_os(context: &str) -> Self {
        Error::io(context, &std::io::Error::last_os_error())
    }

    /// A transport error built from an `io::Error`, with context.
    pub fn io(context: &str, err: &std::io::Error) -> Self {
        Error::Transport(format!("{context}: {err}"))
    }

    /// The message without the kind.
    pub fn message(&self) -> &str {
        match self {
            Error::Config(m) | Error::Command(m) | Error::Transport(m) | Error::State(m) => m,
        }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let kind = match self {
            Error::Config(_) => "configuration error",
            Error::Command(_) => "command refused",
            Error::Transport(_) => "transport error",
            Error::State(_) => "state error",
        };
        write!(f, "{kind}: {}", self.message())
    }
}

impl std::error::Error for Error {}

/// Longest piece of caller input quoted in an error message, characters.
pub const CLIP_CHARS: usize = 60;

/// Quote `s` for an error message, cut to [`CLIP_CHARS`] characters with its
/// full length noted, so a huge argument never becomes a huge exception
/// (`test_f8_errors_do_not_echo_unbounded_input`).
pub fn clip(s: &str) -> String {
    let n = s.chars().count();
    if n <= CLIP_CHARS {
        format!("{s:?}")
    } else {
        let head: String = s.chars().take(CLIP_CHARS / 2).collect();
        format!("{head:?}... ({n} characters)")
    }
}

/// Crate-wide result alias.
pub type Result<T> = std::result::Result<T, Error>;
