//! Writing to stdout and stderr without panicking: `println!` panics when the reader of a
//! pipe has gone (`geocal check X | head -1`). Output to a closed stdout is an error the
//! caller returns and `main` ends on quietly (`is_broken_pipe`); output to a closed stderr is
//! dropped.

/// `println!` to stdout, as an `std::io::Result`.
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::console::write_out(format_args!("{}\n", format_args!($($arg)*)))
    };
}

/// `print!` to stdout, as an `std::io::Result`.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::console::write_out(format_args!($($arg)*))
    };
}

/// `eprintln!` that drops what a closed stderr cannot take.
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {
        $crate::console::write_err(format_args!("{}\n", format_args!($($arg)*)))
    };
}

pub fn write_out(text: std::fmt::Arguments<'_>) -> std::io::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    out.write_fmt(text).and_then(|()| out.flush())
}

pub fn write_err(text: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let _ = std::io::stderr().lock().write_fmt(text);
}

/// The error is (caused by) a write to a pipe whose reader has gone.
pub fn is_broken_pipe(error: &anyhow::Error) -> bool {
    error.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

/// What the command line prints for an error (the Python package raises the same text): the
/// error and its causes, one cause per line, outermost first. Many messages embed their
/// source's text as a suffix: that suffix is cut from the line, so no cause shows twice.
pub fn error_text(e: &anyhow::Error) -> String {
    let mut lines: Vec<String> = Vec::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if let Some(last) = lines.last_mut() {
            if let Some(head) = last.strip_suffix(&format!(": {text}")) {
                *last = head.to_owned();
            } else if last.contains(&text) {
                continue;
            }
        }
        lines.push(text);
    }
    let mut out = String::new();
    for (i, line) in lines.iter().enumerate() {
        out += if i == 0 { "error: " } else { "  because: " };
        out += line;
        out += "\n";
    }
    out
}
