//! `tinybms`: the desktop tool (`cargo tinybms --help`). Everything is in
//! `host_tests::tool`.

fn main() -> std::process::ExitCode {
    host_tests::tool::end_quietly_on_a_closed_pipe();
    let args: Vec<String> = std::env::args().skip(1).collect();
    host_tests::tool::main(&args)
}
