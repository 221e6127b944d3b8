//! `tinybms`, the desktop tool (`tinybms --help`). Everything is in the
//! library ([`tinybms::main`]).

fn main() -> std::process::ExitCode {
    tinybms::end_quietly_on_a_closed_pipe();
    let args: Vec<String> = std::env::args().skip(1).collect();
    tinybms::main(&args)
}
