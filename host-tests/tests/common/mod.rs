//! Helpers of the end-to-end tests: the built `sim` and `tinybms` binaries as
//! child processes, bounded in time, killed when their guards drop.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

/// Longest any one tool run may take before the test fails (not a timing
/// assertion: only a bound so a hang fails instead of blocking CI).
pub const RUN_LIMIT: Duration = Duration::from_secs(120);

/// A running `sim`, killed on drop.
pub struct Sim {
    pub child: Child,
    pub path: String,
}

impl Sim {
    pub fn start(args: &[&str]) -> Sim {
        let mut child = Command::new(env!("CARGO_BIN_EXE_sim"))
            .args(args)
            // A safety net: the sim ends by itself even if this process dies.
            .args(["--duration", "600s"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start sim");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut r = BufReader::new(stdout);
            let mut line = String::new();
            let _ = r.read_line(&mut line);
            let _ = tx.send(line);
            // Keep draining so the sim never blocks on a full pipe.
            let mut sink = Vec::new();
            let _ = r.read_to_end(&mut sink);
        });
        let line = rx
            .recv_timeout(Duration::from_secs(60))
            .expect("sim printed its pty path");
        let path = line.trim().to_string();
        assert!(path.starts_with("/dev/"), "first line: {line:?}");
        Sim { child, path }
    }
}

impl Drop for Sim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub struct Out {
    pub code: i32,
    pub stdout: String,
    pub stderr: String,
}

impl std::fmt::Display for Out {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "exit {}\n--- stdout\n{}\n--- stderr\n{}",
            self.code, self.stdout, self.stderr
        )
    }
}

/// The `tinybms` binary under test: `TINYBMS_BIN` (to show that a test
/// fails on an older build), or the one the workspace's `cargo test` builds
/// beside `sim` (the tool is its own crate, `host-tests/tool`; its own tests
/// make cargo build it). A missing binary, or one older than a source it is
/// built from, fails the test with the command that makes it.
pub fn tinybms_bin() -> String {
    if let Ok(bin) = std::env::var("TINYBMS_BIN") {
        return bin;
    }
    let bin = std::path::Path::new(env!("CARGO_BIN_EXE_sim"))
        .with_file_name(format!("tinybms{}", std::env::consts::EXE_SUFFIX));
    let build = "cargo build -p tinybms (the workspace's `cargo test` builds it)";
    let built = std::fs::metadata(&bin)
        .and_then(|m| m.modified())
        .unwrap_or_else(|e| panic!("{}: {e}: {build}", bin.display()));
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let sources = [
        "tool/src",
        "desk/src",
        "rules/src",
        "../firmware/src",
        "../protocol-core/src",
    ];
    if let Some(newer) = sources
        .iter()
        .find_map(|d| newer_than(&root.join(d), built))
    {
        panic!(
            "{} is older than {}: {build}",
            bin.display(),
            newer.display()
        );
    }
    bin.display().to_string()
}

/// A file under `dir` modified after `t`, if any.
fn newer_than(dir: &std::path::Path, t: std::time::SystemTime) -> Option<std::path::PathBuf> {
    for e in std::fs::read_dir(dir).ok()?.flatten() {
        let path = e.path();
        if path.is_dir() {
            if let Some(p) = newer_than(&path, t) {
                return Some(p);
            }
        } else if e.metadata().and_then(|m| m.modified()).is_ok_and(|m| m > t) {
            return Some(path);
        }
    }
    None
}

/// Runs `tinybms args`, with `input` on stdin, killed after [`RUN_LIMIT`].
pub fn tinybms_with_input(args: &[&str], input: &str) -> Out {
    tinybms_limited(args, input, RUN_LIMIT)
        .unwrap_or_else(|| panic!("tinybms {args:?} did not finish within {RUN_LIMIT:?}"))
}

/// Runs `tinybms args`, with `input` on stdin; `None` when it had not
/// finished after `limit` (then it is killed).
pub fn tinybms_limited(args: &[&str], input: &str, limit: Duration) -> Option<Out> {
    let mut cmd = Command::new(tinybms_bin());
    cmd.args(args).stdin(Stdio::piped());
    let mut running = Captured::start(&mut cmd);
    let mut stdin = running.child.stdin.take().unwrap();
    let _ = stdin.write_all(input.as_bytes());
    drop(stdin);
    let (status, stdout, stderr) = running.wait(limit)?;
    Some(Out {
        code: status.code().unwrap_or(-1),
        stdout,
        stderr,
    })
}

/// A child process whose stdout and stderr are read to their end as it runs
/// (so a full pipe never stalls it).
pub struct Captured {
    pub child: Child,
    out: std::thread::JoinHandle<String>,
    err: std::thread::JoinHandle<String>,
}

impl Captured {
    /// Starts `cmd` with stdout and stderr piped (stdin as `cmd` says).
    pub fn start(cmd: &mut Command) -> Self {
        let mut child = cmd
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start the program under test");
        let read = |mut r: Box<dyn Read + Send>| {
            std::thread::spawn(move || {
                let mut s = Vec::new();
                let _ = r.read_to_end(&mut s);
                String::from_utf8_lossy(&s).into_owned()
            })
        };
        let out = read(Box::new(child.stdout.take().unwrap()));
        let err = read(Box::new(child.stderr.take().unwrap()));
        Self { child, out, err }
    }

    /// Waits for its exit, at most `limit` (then kills it: `None`): the
    /// status, stdout and stderr.
    pub fn wait(mut self, limit: Duration) -> Option<(std::process::ExitStatus, String, String)> {
        let start = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            if start.elapsed() > limit {
                let _ = self.child.kill();
                let _ = self.child.wait();
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        Some((status, self.out.join().unwrap(), self.err.join().unwrap()))
    }
}

pub fn tinybms(args: &[&str]) -> Out {
    tinybms_with_input(args, "")
}

pub fn json_lines(text: &str) -> Vec<Value> {
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

pub fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("tinybms-e2e-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Runs `git ARGS` in `dir` (a scratch repository: no repository above it is
/// seen, no signing, a fixed author); fails the test when git does.
pub fn git(dir: &std::path::Path, args: &[&str]) {
    let o = std::process::Command::new("git")
        .args([
            "-c",
            "user.name=t",
            "-c",
            "user.email=t@t",
            "-c",
            "commit.gpgsign=false",
        ])
        .args(args)
        .current_dir(dir)
        .env("GIT_CEILING_DIRECTORIES", dir.parent().unwrap())
        .output()
        .unwrap();
    assert!(o.status.success(), "git {args:?}: {o:?}");
}
