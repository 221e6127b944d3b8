//! `replay FILE` (or `-` for standard input): decodes a `.tbms` capture and prints
//! one JSON object per request, received frame or error, then a summary line.
//! See `docs/capture-format.md`.
//!
//! Exit status: 0 when the capture was read (decode errors are data), 1 when the
//! file cannot be read or is malformed, 2 on a usage error.

use std::io::{self, Read, Write};
use std::process::ExitCode;

use host_tests::replay::replay;
use tinybms_desk::capture::parse_capture_bytes;

const USAGE: &str = "usage: replay FILE   (FILE = a .tbms capture, or - for standard input)";

fn main() -> ExitCode {
    tinybms_desk::end_quietly_on_a_closed_pipe();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = match args.as_slice() {
        [a] if a == "-h" || a == "--help" => {
            println!("{USAGE}");
            return ExitCode::SUCCESS;
        }
        [a] => a.clone(),
        _ => {
            eprintln!("{USAGE}");
            return ExitCode::from(2);
        }
    };
    let (name, bytes) = if path == "-" {
        let mut buf = Vec::new();
        if let Err(e) = io::stdin().lock().read_to_end(&mut buf) {
            eprintln!("replay: cannot read standard input: {e}");
            return ExitCode::FAILURE;
        }
        ("<stdin>".to_owned(), buf)
    } else {
        match std::fs::read(&path) {
            Ok(b) => (path.clone(), b),
            Err(e) => {
                eprintln!("replay: cannot read {path}: {e}");
                return ExitCode::FAILURE;
            }
        }
    };
    let capture = match parse_capture_bytes(&bytes) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("replay: {name}:{}: {}", e.line, e.message);
            return ExitCode::FAILURE;
        }
    };
    let stdout = io::stdout();
    let mut out = io::BufWriter::new(stdout.lock());
    let written = replay(&capture)
        .iter()
        .try_for_each(|v| writeln!(out, "{v}"))
        .and_then(|()| out.flush());
    match written {
        Ok(()) => ExitCode::SUCCESS,
        // A closed pipe (`replay x | head`) is not an error of ours.
        Err(e) if e.kind() == io::ErrorKind::BrokenPipe => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("replay: cannot write output: {e}");
            ExitCode::FAILURE
        }
    }
}
