//! `tinybms keygen`, `tinybms sign`, `tinybms public-key` and `tinybms
//! update`: update files signed with Ed25519 (`tinybms_firmware::update::file`)
//! and their transfer to a bridge, over its USB port or its update port on
//! the network, chunk by chunk with the offset the bridge asks for next.

use std::io::{IsTerminal, Write as _};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use base64::Engine as _;
use ed25519_dalek::{Signer, SigningKey};
use serde_json::json;
use sha2::{Digest, Sha256};
use tinybms_firmware::host_link::schema::{HostLine, Update};
use tinybms_firmware::update::file::{self, Header, HEADER_LEN, SIGNED_LEN};
use tinybms_firmware::update::transfer::CHUNK_MAX;

use crate::client::Client;
use crate::{ToolError, ToolResult};
use tinybms_firmware::host_link::schema::Read;

/// Bytes per chunk: as many as the bridge's command line carries in base64.
pub const CHUNK: usize = CHUNK_MAX;
/// A chunk unanswered this long is sent again.
const ANSWER_WAIT: Duration = Duration::from_secs(2);
/// A chunk sent this many times without an answer ends the transfer.
const TRIES: u32 = 10;
/// The bridge's update port on the network (images with Wi-Fi).
pub const TCP_PORT: u16 = tinybms_firmware::update::TCP_PORT;

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// A signing key from its file: 64 hex digits (the seed), nothing else but
/// white space.
pub fn read_signing_key(path: &Path) -> ToolResult<SigningKey> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| ToolError::usage(format!("cannot read the key `{}`: {e}", path.display())))?;
    let seed = tinybms_firmware::update::parse_key(text.trim().as_bytes()).ok_or_else(|| {
        ToolError::usage(format!(
            "`{}` is not a signing key (64 hex digits, as `tinybms keygen` writes)",
            path.display()
        ))
    })?;
    Ok(SigningKey::from_bytes(&seed))
}

/// `tinybms keygen OUT`: a new key pair, OUT (private, only the owner may
/// read it) and OUT.pub.
pub fn keygen(out: &Path) -> ToolResult<()> {
    let pubfile = PathBuf::from(format!("{}.pub", out.display()));
    if out.exists() || pubfile.exists() {
        return Err(ToolError::usage(format!(
            "`{}` or its .pub exists: a key is never overwritten",
            out.display()
        )));
    }
    let mut seed = [0u8; 32];
    getrandom::fill(&mut seed).map_err(|e| ToolError::failed(format!("no randomness: {e}")))?;
    let key = SigningKey::from_bytes(&seed);
    let public = hex(&key.verifying_key().to_bytes());
    write_private(out, &format!("{}\n", hex(&seed)))?;
    std::fs::write(&pubfile, format!("{public}\n"))
        .map_err(|e| ToolError::failed(format!("{}: {e}", pubfile.display())))?;
    println!(
        "private key: {} (keep it; anyone with it can sign updates your bridges take)",
        out.display()
    );
    println!("public key:  {public}");
    println!("Let a bridge take updates you sign: tinybms config PORT update_key={public}");
    println!("or build it trusting the key: TINYBMS_UPDATE_KEY={public} cargo build --release");
    Ok(())
}

fn write_private(path: &Path, text: &str) -> ToolResult<()> {
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(0o600);
    }
    let mut f = o
        .open(path)
        .map_err(|e| ToolError::failed(format!("{}: {e}", path.display())))?;
    f.write_all(text.as_bytes())
        .map_err(|e| ToolError::failed(format!("{}: {e}", path.display())))
}

/// `tinybms public-key KEY`: the public key of a signing key.
pub fn public_key(key: &Path) -> ToolResult<()> {
    let k = read_signing_key(key)?;
    println!("{}", hex(&k.verifying_key().to_bytes()));
    Ok(())
}

/// What `tinybms sign` puts in the header besides the image.
#[derive(Debug, Clone)]
pub struct SignArgs {
    /// The signing key's file.
    pub key: PathBuf,
    /// The app image (`tinybms-BOARD-app.bin`).
    pub image: PathBuf,
    /// The update file to write.
    pub out: PathBuf,
    /// esp32c3 or esp32c6.
    pub chip: String,
    /// The board's name.
    pub board: String,
    /// The version the image reports.
    pub version: String,
    /// What is built in, comma-separated.
    pub features: String,
    /// What it was built from.
    pub build: String,
}

/// The update file of `image` (header signed with `key`).
pub fn sign_bytes(key: &SigningKey, image: &[u8], a: &SignArgs) -> ToolResult<Vec<u8>> {
    if !file::image_start_ok(image, &a.chip) {
        return Err(ToolError::usage(format!(
            "`{}` is not an app image for {} (magic E9, chip id, app descriptor)",
            a.image.display(),
            a.chip
        )));
    }
    let hash: [u8; 32] = Sha256::digest(image).into();
    let len = u32::try_from(image.len()).map_err(|_| ToolError::usage("the image is too large"))?;
    let mut h = file::unsigned_header(
        len,
        &hash,
        &a.chip,
        &a.board,
        &a.features,
        &a.version,
        &a.build,
    )
    .map_err(|r| ToolError::usage(format!("the header: {}", r.words())))?;
    let sig = key.sign(&h[..SIGNED_LEN]);
    h[SIGNED_LEN..].copy_from_slice(&sig.to_bytes());
    let mut out = h.to_vec();
    out.extend_from_slice(image);
    Ok(out)
}

/// `tinybms sign`.
pub fn sign(a: &SignArgs) -> ToolResult<()> {
    let key = read_signing_key(&a.key)?;
    let image = std::fs::read(&a.image)
        .map_err(|e| ToolError::usage(format!("cannot read `{}`: {e}", a.image.display())))?;
    let bytes = sign_bytes(&key, &image, a)?;
    std::fs::write(&a.out, &bytes)
        .map_err(|e| ToolError::failed(format!("{}: {e}", a.out.display())))?;
    println!(
        "{}: {} {} {} ({} bytes), signed by {}",
        a.out.display(),
        a.chip,
        a.board,
        a.version,
        image.len(),
        hex(&key.verifying_key().to_bytes())
    );
    Ok(())
}

/// An update file read and its header parsed (not checked against any key:
/// the bridge does that).
pub fn read_update(path: &Path) -> ToolResult<(Vec<u8>, Header)> {
    let bytes = std::fs::read(path)
        .map_err(|e| ToolError::usage(format!("cannot read `{}`: {e}", path.display())))?;
    let head: &[u8; HEADER_LEN] = bytes
        .get(..HEADER_LEN)
        .and_then(|h| h.try_into().ok())
        .ok_or_else(|| {
            ToolError::usage(format!(
                "`{}` is too short for an update file",
                path.display()
            ))
        })?;
    let h = Header::parse(head)
        .map_err(|r| ToolError::usage(format!("`{}`: {}", path.display(), r.words())))?;
    Ok((bytes, h))
}

/// The `update` line answering `req`.
fn answer(c: &mut Client, req: u32, what: &str) -> ToolResult<Option<Update<Read>>> {
    let end = Instant::now() + ANSWER_WAIT;
    match c.recv_for(req, end, what) {
        Ok(r) => match r.line {
            HostLine::Update(u) => Ok(Some(u)),
            _ => Err(ToolError::failed(format!(
                "the bridge answered `{what}` with another line"
            ))),
        },
        Err(e) if e.message.contains("no answer") => Ok(None),
        Err(e) => Err(e),
    }
}

fn ended(u: &Update<Read>) -> ToolError {
    let why = u.detail.clone().unwrap_or_else(|| "no reason given".into());
    ToolError::failed(format!("the bridge refused the update: {why}"))
}

/// Progress on stderr: a bar on a terminal, a line every 10 % otherwise.
struct Progress {
    total: usize,
    tty: bool,
    shown: usize,
    start: Instant,
}

impl Progress {
    fn show(&mut self, at: usize) {
        let pct = at * 100 / self.total.max(1);
        if self.tty {
            let filled = pct * 30 / 100;
            eprint!(
                "\r[{}{}] {pct:>3} %  {} of {} KiB",
                "#".repeat(filled),
                " ".repeat(30 - filled),
                at / 1024,
                self.total / 1024
            );
        } else if pct >= self.shown + 10 || (at == self.total && self.shown < 100) {
            self.shown = pct - pct % 10;
            eprintln!("{pct:>3} %  {} of {} KiB", at / 1024, self.total / 1024);
        }
    }
}

/// Sends the update file `bytes` to the bridge on `c`: the header is
/// checked by the bridge first (`check`: only that, nothing is written).
/// Returns the version installed.
pub fn send(
    c: &mut Client,
    bytes: &[u8],
    downgrade: bool,
    check: bool,
    quiet: bool,
) -> ToolResult<String> {
    let size = bytes.len();
    let req = c.send(
        json!({"cmd": "update_begin", "size": size, "downgrade": downgrade, "check": check}),
    )?;
    let mut a = answer(c, req, "update_begin")?.ok_or_else(|| {
        ToolError::failed("no answer to update_begin (an image without updates?)")
    })?;
    let mut progress = Progress {
        total: size,
        tty: !quiet && std::io::stderr().is_terminal(),
        shown: 0,
        start: Instant::now(),
    };
    let mut tries = 0;
    let mut last_at = usize::MAX;
    loop {
        match a.state.as_str() {
            "acceptable" => return Ok(String::new()),
            "ended" => return Err(ended(&a)),
            "not_started" => {
                return Err(ToolError::failed(
                    "the bridge dropped the transfer (another one began, or it restarted)",
                ))
            }
            "bad_chunk" => {
                return Err(ToolError::failed("the bridge refused a chunk as malformed"))
            }
            "next" | "busy" => {}
            other => {
                return Err(ToolError::failed(format!(
                    "unexpected update state `{other}`"
                )))
            }
        }
        let at = a.at.unwrap_or(0) as usize;
        if at >= size {
            break;
        }
        if a.state == "busy" {
            std::thread::sleep(Duration::from_millis(10));
        }
        if at == last_at && a.state != "busy" {
            tries += 1;
        } else if at != last_at {
            tries = 0;
        }
        last_at = at;
        if tries >= TRIES {
            return Err(ToolError::failed(format!(
                "the bridge keeps asking for offset {at}: giving up"
            )));
        }
        if !quiet {
            progress.show(at);
        }
        // Within the header, or within one sector of the image.
        let boundary = if at < HEADER_LEN {
            HEADER_LEN
        } else {
            HEADER_LEN + ((at - HEADER_LEN) / 4096 + 1) * 4096
        };
        let end = (at + CHUNK).min(size).min(boundary);
        let data = base64::engine::general_purpose::STANDARD.encode(&bytes[at..end]);
        let mut sent = 0;
        a = loop {
            let req = c.send(json!({"cmd": "update_chunk", "at": at, "data": data}))?;
            match answer(c, req, "update_chunk")? {
                Some(u) => break u,
                None => {
                    sent += 1;
                    if sent >= TRIES {
                        return Err(ToolError::failed(format!(
                            "no answer to the chunk at {at} after {TRIES} tries"
                        )));
                    }
                }
            }
        };
        if crate::interrupted() {
            let req = c.send(json!({"cmd": "update_cancel"}))?;
            let _ = answer(c, req, "update_cancel");
            return Err(crate::interrupted_error());
        }
    }
    if !quiet {
        progress.show(size);
        if progress.tty {
            eprintln!();
        }
        eprintln!(
            "sent {} KiB in {:.1} s; the bridge checks the image's hash and makes it the one to boot…",
            size / 1024,
            progress.start.elapsed().as_secs_f64()
        );
    }
    // The last sector, the hash and otadata: asked until it says.
    let end = Instant::now() + Duration::from_secs(30);
    while Instant::now() < end {
        let req = c.send(json!({"cmd": "update_status"}))?;
        if let Some(u) = answer(c, req, "update_status")? {
            match u.phase.as_str() {
                "installed" => return Ok(u.version.unwrap_or_default()),
                "idle" => return Err(ended(&u)),
                _ => {}
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    Err(ToolError::failed(
        "the bridge did not finish the update in 30 s",
    ))
}
