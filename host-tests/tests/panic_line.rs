//! The line a panicking chip writes to the host (UART0 boards): a `log` line
//! at `warn` that the host's own line types read, with every return address.

use tinybms_firmware::host_link::panic::{write_line, FRAMES_MAX};
use tinybms_firmware::host_link::schema::HostLine;

fn line(pcs: &[u32]) -> Vec<u8> {
    let mut out = Vec::new();
    write_line(pcs.iter().copied(), |b: &[u8]| out.extend_from_slice(b));
    out
}

#[test]
fn the_panic_line_is_a_log_line_the_host_reads() {
    let bytes = line(&[0x4200_1a2b, 0x0000_0000, 0xffff_ffff]);
    assert_eq!(bytes[0], b'\n', "it ends whatever line was cut");
    let text = std::str::from_utf8(&bytes[1..]).unwrap();
    assert!(text.ends_with("\"}\n"));
    let parsed: HostLine = serde_json::from_str(text.trim_end()).unwrap();
    let HostLine::Log(log) = parsed else {
        panic!("not a log line: {text}");
    };
    assert_eq!(log.level, "warn");
    assert_eq!(
        log.text,
        "panic, restarting; backtrace 0x42001a2b 0x00000000 0xffffffff"
    );
}

#[test]
fn the_panic_line_keeps_at_most_its_frames() {
    let many: Vec<u32> = (0..40).collect();
    let text = String::from_utf8(line(&many)).unwrap();
    assert_eq!(text.matches(" 0x").count(), FRAMES_MAX);
    let none = String::from_utf8(line(&[])).unwrap();
    assert!(none.contains("\"text\":\"panic, restarting; backtrace\""));
}
