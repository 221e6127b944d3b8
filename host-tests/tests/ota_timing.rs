//! An update does not move the bridge's work: the same pack, seed and
//! inverter in virtual time, once with an update sent over the host link as
//! fast as the bridge takes it, once with an `update_status` line at each of
//! the same instants instead (a host line wakes the station and hands it the
//! UART's bytes sooner, on the chip as here: the same lines, so the only
//! difference is the update) — every request to the BMS and every CAN frame
//! at the same microsecond, with the same bytes. The update's flash work (an
//! erase stops the CPU 45 ms, a program 15 ms, an `otadata` write 45 ms: the
//! harness stalls the clock that long) goes only into the gaps the BMS poll
//! and the CAN output leave.

use base64::Engine as _;
use ed25519_dalek::{Signer, SigningKey};
use host_tests::closed_loop::ClosedLoop;
use host_tests::sim::PackModel;
use sha2::{Digest, Sha256};
use tinybms_desk::flash::RamFlash;
use tinybms_desk::ota::ChipFlash;
use tinybms_firmware::config::Config;
use tinybms_firmware::update::file::{self, SIGNED_LEN};
use tinybms_firmware::update::otadata::Cause;

const S: u64 = 1_000_000;

fn key() -> SigningKey {
    SigningKey::from_bytes(&[5; 32])
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

fn update_file() -> Vec<u8> {
    let mut img: Vec<u8> = (0..300_000usize).map(|i| (i * 11) as u8).collect();
    img[0] = 0xE9;
    img[32..36].copy_from_slice(&0xABCD_5432u32.to_le_bytes());
    img[48..80].fill(0);
    img[48..53].copy_from_slice(b"0.9.0");
    img[12..14].copy_from_slice(&5u16.to_le_bytes());
    let hash: [u8; 32] = Sha256::digest(&img).into();
    let mut h = file::unsigned_header(
        img.len() as u32,
        &hash,
        "esp32c3",
        "c3-supermini",
        "can,host-link",
        "0.9.0",
        "t",
    )
    .unwrap();
    let sig = key().sign(&h[..SIGNED_LEN]);
    h[SIGNED_LEN..].copy_from_slice(&sig.to_bytes());
    [h.to_vec(), img].concat()
}

/// The run: its BMS requests, its CAN frames, when the update was installed
/// (`None`: no update), its flash operations, when host lines went in.
type Run = (
    Vec<(u64, Vec<u8>)>,
    Vec<(u64, u16)>,
    Option<u64>,
    usize,
    Vec<u64>,
);

/// With an update (`lines_at` `None`), or with `update_status` lines at
/// `lines_at` instead.
fn run(lines_at: Option<&[u64]>, end: u64) -> Run {
    let with_update = lines_at.is_none();
    // The same record in both runs: the owner's update key registered.
    let flash = RamFlash::new();
    let record = Config {
        update_key: {
            let mut s = heapless::String::new();
            s.push_str(&hex(&key().verifying_key().to_bytes())).unwrap();
            s
        },
        ..Config::default()
    };
    embassy_futures::block_on(tinybms_desk::flash::store(flash.clone()).save(&record)).unwrap();
    // The bridge stands for an ESP32-C3 SuperMini (what the file names).
    let identity = tinybms_firmware::identity::Identity {
        chip: "esp32c3",
        board: "ESP32-C3 SuperMini",
        ..tinybms_firmware::identity::Identity::desktop(
            "esp32c3",
            tinybms_firmware::identity::Features {
                can: true,
                host_link: true,
                ..Default::default()
            },
        )
    };
    let mut l = ClosedLoop::from_flash_as(PackModel::LiFePO4_16S, 11, flash, 100.0, identity);
    l.h.tx_log = Some(Vec::new());
    // The chip's flash with the firmware's partition table.
    let chip = tinybms_desk::ota::chip_flash();
    let image = tinybms_desk::ota::boot(&chip, Cause::PowerCut);
    l.h.station.set_ota(image.ota);
    l.h.ota = Some(ChipFlash(chip));
    let file = update_file();
    let mut installed = None;
    let mut sent = Vec::new();
    if with_update {
        l.run_until(5 * S);
        let mut at: Option<usize> = None;
        let mut asked = 0usize;
        sent.push(l.h.now);
        l.host_line(&format!(
            r#"{{"cmd":"update_begin","size":{},"req":1}}"#,
            file.len()
        ));
        while l.h.now < end && !l.h.restart_requested {
            // The last answer says where to go on.
            if let Some(v) = l
                .host
                .as_ref()
                .unwrap()
                .lines
                .iter()
                .rev()
                .find(|v| v["type"] == "update")
            {
                if v["state"] == "ended" {
                    panic!("the update ended: {v}");
                }
                at = v["at"].as_u64().map(|a| a as usize).or(at);
            }
            let next = at.unwrap_or(0);
            if next < file.len() {
                let e = (next + 128).min(file.len());
                let data = base64::engine::general_purpose::STANDARD.encode(&file[next..e]);
                sent.push(l.h.now);
                l.host_line(&format!(
                    r#"{{"cmd":"update_chunk","at":{next},"data":"{data}"}}"#
                ));
                asked += 1;
            }
            l.run_until(l.h.now + 2_000);
        }
        installed = l.h.restarted_at;
        let _ = asked;
    } else {
        for &t in lines_at.unwrap_or(&[]) {
            // (A line that came while a request was on the wire goes in at
            // its end, as the station task takes it then.)
            l.run_until(t);
            l.host_line(r#"{"cmd":"update_status"}"#);
        }
        l.run_until(end);
    }
    let ops = l.h.flash_ops.len();
    let tx = l.h.tx_log.take().unwrap();
    (tx, l.sent_ids.clone(), installed, ops, sent)
}

#[test]
fn the_bms_poll_and_the_can_frames_keep_their_time_while_an_update_comes() {
    let end = 60 * S;
    let (tx_u, can_u, installed, ops, lines) = run(None, end);
    let at = installed.expect("the update was installed");
    assert!(ops >= 30, "{ops} flash operations");
    let (tx_b, can_b, _, ops_b, _) = run(Some(&lines), at);
    assert_eq!(ops_b, 0);
    // Up to the restart into the new image.
    let tx_u: Vec<_> = tx_u.into_iter().filter(|(t, _)| *t < at).collect();
    let tx_b: Vec<_> = tx_b.into_iter().filter(|(t, _)| *t < at).collect();
    let can_u: Vec<_> = can_u.into_iter().filter(|(t, _)| *t < at).collect();
    let can_b: Vec<_> = can_b.into_iter().filter(|(t, _)| *t < at).collect();
    eprintln!(
        "update installed at {:.3} s after {} host lines and {ops} flash operations; {} BMS requests and {} CAN frames up to then, in both runs",
        at as f64 / 1e6,
        lines.len(),
        tx_b.len(),
        can_b.len()
    );
    assert_eq!(tx_u.len(), tx_b.len(), "BMS requests");
    for (i, (u, b)) in tx_u.iter().zip(&tx_b).enumerate() {
        assert_eq!(
            u, b,
            "BMS request {i}: with the update at {} µs, without at {} µs",
            u.0, b.0
        );
    }
    assert_eq!(can_u, can_b, "the CAN frames' times and ids");
    assert!(can_b.len() >= 100 && tx_b.len() >= 100);
}
