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
use tinybms_firmware::host_link::schema::{Hello, HostLine, Update};
use tinybms_firmware::update::file::{self, Header, HEADER_LEN, SIGNED_LEN};
use tinybms_firmware::update::key_text::{self, KeyText};
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

/// A key file's text, understood (`tinybms_firmware::update::key_text`: a
/// public key is 64 hex digits, a private key 128).
fn read_key_text(path: &Path) -> ToolResult<KeyText> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| ToolError::failed(format!("cannot read the key `{}`: {e}", path.display())))?;
    key_text::parse(&text)
        .map_err(|e| ToolError::failed(format!("`{}`: {}", path.display(), e.words())))
}

/// A signing key from its file: a private key, 128 hex digits (`tinybms
/// keygen`), whose public half is the seed's. A public key is refused with
/// words that say which is which.
pub fn read_signing_key(path: &Path) -> ToolResult<SigningKey> {
    match read_key_text(path)? {
        KeyText::Public(_) => Err(ToolError::failed(format!(
            "`{}` holds a PUBLIC key (64 hex digits): it only checks signatures; sign with \
             the private key (128 hex digits: the file tinybms keygen wrote without .pub)",
            path.display()
        ))),
        KeyText::Private { seed, public } => {
            let key = SigningKey::from_bytes(&seed);
            if key.verifying_key().to_bytes() == public {
                Ok(key)
            } else {
                Err(ToolError::failed(format!(
                    "`{}` is damaged: its two halves do not belong together (the public key \
                     written in it is not its private key's)",
                    path.display()
                )))
            }
        }
    }
}

/// The text of a private key file (128 hex digits: seed, then public key).
fn private_file(seed: &[u8; 32], public: &[u8; 32], pubfile: &Path) -> String {
    format!(
        "# tinybms update signing key: PRIVATE. Anyone with this file can sign firmware\n\
         # your bridges take: keep it safe, never give it to a bridge or post it.\n\
         # Its public key (what bridges are given) is in {}.\n{}\n{}\n",
        pubfile.display(),
        hex(seed),
        hex(public)
    )
}

/// The text of a public key file (64 hex digits).
fn public_file(public: &[u8; 32]) -> String {
    let p = hex(public);
    format!(
        "# tinybms update public key: give it to a bridge to trust what its private key\n\
         # signs (tinybms config PORT update_key={p}).\n{p}\n"
    )
}

/// `tinybms keygen OUT`: a new key pair, OUT (private, only the owner may
/// read it) and OUT.pub.
pub fn keygen(out: &Path) -> ToolResult<()> {
    let pubfile = PathBuf::from(format!("{}.pub", out.display()));
    if out.exists() || pubfile.exists() {
        return Err(ToolError::failed(format!(
            "`{}` or its .pub exists: a key is never overwritten",
            out.display()
        )));
    }
    let mut seed = [0u8; 32];
    getrandom::fill(&mut seed).map_err(|e| ToolError::failed(format!("no randomness: {e}")))?;
    let key = SigningKey::from_bytes(&seed);
    let public_bytes = key.verifying_key().to_bytes();
    let public = hex(&public_bytes);
    write_private(out, &private_file(&seed, &public_bytes, &pubfile))?;
    std::fs::write(&pubfile, public_file(&public_bytes))
        .map_err(|e| ToolError::failed(format!("{}: {e}", pubfile.display())))?;
    println!(
        "private key: {} (keep it secret; anyone with it can sign updates your bridges take)",
        out.display()
    );
    println!("public key:  {} = {public}", pubfile.display());
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

/// `tinybms public-key KEY`: the public key of a private key. Given a
/// public key it says so (and derives nothing from it).
pub fn public_key(key: &Path) -> ToolResult<()> {
    if let KeyText::Public(p) = read_key_text(key)? {
        return Err(ToolError::failed(format!(
            "`{}` already is a public key: {} (give that to a bridge; \
             public-key takes the private key, 128 hex digits)",
            key.display(),
            hex(&p)
        )));
    }
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
    /// The version the image reports: read from the image; when given, it
    /// must be the image's.
    pub version: Option<String>,
    /// What is built in, comma-separated: read from the image; when given,
    /// it must be the image's.
    pub features: Option<String>,
    /// What it was built from: read from the image (an image from before
    /// images named their build takes this); when given, it must be the
    /// image's.
    pub build: Option<String>,
}

/// The project name of an image built before images carried their build in
/// their descriptor (the crate's name): no build.
const OLD_PROJECT_NAME: &str = "tinybms-firmware";

/// A field of the header from the image's own descriptor, or else from the
/// command line; both, and they must agree.
fn from_image(
    what: &str,
    image: Option<&str>,
    given: Option<&str>,
    flag: &str,
) -> ToolResult<String> {
    match (image, given) {
        (Some(i), Some(g)) if i != g => Err(ToolError::failed(format!(
            "the image says its {what} is `{i}`, not `{g}`: a header must say what the image \
             reports (leave out {flag})"
        ))),
        (Some(i), _) => Ok(i.to_string()),
        (None, Some(g)) => Ok(g.to_string()),
        (None, None) => Err(ToolError::failed(format!(
            "the image does not say its {what}: give {flag}"
        ))),
    }
}

/// The update file of `image` (header signed with `key`).
pub fn sign_bytes(key: &SigningKey, image: &[u8], a: &SignArgs) -> ToolResult<Vec<u8>> {
    if !file::image_start_ok(image, &a.chip) {
        return Err(ToolError::failed(format!(
            "`{}` is not an app image for {} (magic E9, chip id, app descriptor)",
            a.image.display(),
            a.chip
        )));
    }
    let version = from_image(
        "version",
        file::image_version(image).filter(|v| !v.is_empty()),
        a.version.as_deref(),
        "--version",
    )?;
    let build = match file::image_build(image).filter(|b| !b.is_empty() && *b != OLD_PROJECT_NAME) {
        None => a.build.clone().unwrap_or_default(),
        known => from_image("build", known, a.build.as_deref(), "--build")?,
    };
    let features = from_image(
        "features",
        tinybms_firmware::identity::features_in_image(image),
        a.features.as_deref(),
        "--features",
    )?;
    let hash: [u8; 32] = Sha256::digest(image).into();
    let len =
        u32::try_from(image.len()).map_err(|_| ToolError::failed("the image is too large"))?;
    let mut h = file::unsigned_header(len, &hash, &a.chip, &a.board, &features, &version, &build)
        .map_err(|r| ToolError::failed(format!("the header: {}", r.words())))?;
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
        .map_err(|e| ToolError::failed(format!("cannot read `{}`: {e}", a.image.display())))?;
    let bytes = sign_bytes(&key, &image, a)?;
    std::fs::write(&a.out, &bytes)
        .map_err(|e| ToolError::failed(format!("{}: {e}", a.out.display())))?;
    let version = file::image_version(&image)
        .map(str::to_string)
        .or_else(|| a.version.clone())
        .unwrap_or_default();
    println!(
        "{}: {} {} {} ({} bytes), signed by {}",
        a.out.display(),
        a.chip,
        a.board,
        version,
        image.len(),
        hex(&key.verifying_key().to_bytes())
    );
    Ok(())
}

/// An update file read and its header parsed (not checked against any key:
/// the bridge does that).
pub fn read_update(path: &Path) -> ToolResult<(Vec<u8>, Header)> {
    let bytes = std::fs::read(path)
        .map_err(|e| ToolError::failed(format!("cannot read `{}`: {e}", path.display())))?;
    let head: &[u8; HEADER_LEN] = bytes
        .get(..HEADER_LEN)
        .and_then(|h| h.try_into().ok())
        .ok_or_else(|| {
            ToolError::failed(format!(
                "`{}` is too short for an update file",
                path.display()
            ))
        })?;
    let h = Header::parse(head)
        .map_err(|r| ToolError::failed(format!("`{}`: {}", path.display(), r.words())))?;
    Ok((bytes, h))
}

/// The whole file, checked before a byte of it goes to a bridge: its length
/// against its header, the image's start for its chip, the image's bytes
/// against the signed hash (a download damaged anywhere is found here).
pub fn check_whole(path: &Path, bytes: &[u8], h: &Header) -> ToolResult<()> {
    let image = bytes.get(HEADER_LEN..).unwrap_or(&[]);
    let bad = |why: &str| {
        Err(ToolError::failed(format!(
            "`{}`: {why}; nothing was sent (download it again)",
            path.display()
        )))
    };
    match image.len().cmp(&(h.image_len as usize)) {
        std::cmp::Ordering::Less => return bad(file::Refusal::Truncated.words()),
        std::cmp::Ordering::Greater => return bad(file::Refusal::Padded.words()),
        std::cmp::Ordering::Equal => {}
    }
    if !file::image_start_ok(image, h.chip()) {
        return bad(file::Refusal::NotAnImage.words());
    }
    let hash: [u8; 32] = Sha256::digest(image).into();
    if hash != h.image_sha256() {
        return bad("damaged: the image's bytes do not give the hash its signature covers");
    }
    Ok(())
}

/// The keys a bridge trusts, from its `hello` (a bridge from before hello
/// said them: `None`).
pub fn trusted_keys(hello: &Hello<Read>) -> Option<Vec<file::Key>> {
    let u = hello.update.as_ref()?;
    let parse = |k: &Option<String>| {
        k.as_deref()
            .and_then(|hex| tinybms_firmware::update::parse_key(hex.as_bytes()))
    };
    Some(
        [parse(&u.built_in_key), parse(&u.owner_key)]
            .into_iter()
            .flatten()
            .collect(),
    )
}

/// The file against the bridge that would take it, as the bridge itself
/// will check it: chip, board, version, the features it runs (those the
/// file lacks must be in `permit.drop`), and the signature with the keys it
/// trusts. The words say what to do.
pub fn check_for(h: &Header, hello: &Hello<Read>, permit: file::Permit) -> ToolResult<()> {
    // The names this tool knows (a later image's unknown ones are ignored).
    let running = hello
        .features
        .iter()
        .filter_map(|n| file::feature_bits(n))
        .fold(0, |a, b| a | b);
    let me = file::Target {
        chip: &hello.chip,
        board: tinybms_firmware::boards::key_of(&hello.board),
        version: &hello.firmware,
        features: running,
        slot_size: u32::MAX,
    };
    match h.check(&me, permit) {
        Ok(()) => {}
        Err(file::Refusal::DropsFeatures) => {
            let lacking = file::lacks(h.features(), running) & !permit.drop;
            let names: Vec<&str> = file::FEATURE_NAMES
                .iter()
                .enumerate()
                .filter(|(i, _)| lacking & (1 << i) != 0)
                .map(|(_, n)| *n)
                .collect();
            let wifi = names.contains(&"wifi");
            return Err(ToolError::failed(format!(
                "this file has no {}, which the bridge runs: after it the bridge would have none{}. \
                 Take the file with the bridge's features ({}){}, or say --drop {} if you mean it; \
                 nothing was sent",
                names.join(", "),
                if wifi {
                    " (no network: no Home Assistant, no update without a cable)"
                } else {
                    ""
                },
                hello.features.join(","),
                if wifi { ": tinybms-BOARD-wifi.tbu" } else { "" },
                names.join(",")
            )));
        }
        Err(file::Refusal::WrongBoard) => {
            return Err(ToolError::failed(format!(
                "this file is for another board ({}; the bridge is a {}, {}): take its board's \
                 file; nothing was sent",
                h.board(),
                hello.board,
                me.board
            )))
        }
        Err(file::Refusal::Older) => {
            return Err(ToolError::failed(format!(
                "this file is {}, older than the running firmware ({}): say --downgrade if you \
                 mean it; nothing was sent",
                h.version(),
                hello.firmware
            )))
        }
        Err(r) => {
            return Err(ToolError::failed(format!(
                "{}; nothing was sent",
                r.words()
            )))
        }
    }
    if let Some(keys) = trusted_keys(hello) {
        if let Err(r) = h.verify(&keys) {
            let trusted: Vec<String> = keys.iter().map(|k| hex(k)).collect();
            // A signature that fails is a stranger's key or a file changed
            // after it was signed (its header included): both are said.
            let changed = if r == file::Refusal::BadSignature {
                "; or the file was changed after it was signed: take it again"
            } else {
                ""
            };
            return Err(ToolError::failed(format!(
                "{} (it trusts {}){changed}; nothing was sent",
                r.words(),
                if trusted.is_empty() {
                    "no key: register yours with update_key over USB".to_string()
                } else {
                    trusted.join(" and ")
                }
            )));
        }
    }
    Ok(())
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
    permit: file::Permit,
    check: bool,
    quiet: bool,
) -> ToolResult<String> {
    let size = bytes.len();
    let mut begin =
        json!({"cmd": "update_begin", "size": size, "downgrade": permit.downgrade, "check": check});
    if permit.drop != 0 {
        let names: Vec<&str> = file::FEATURE_NAMES
            .iter()
            .enumerate()
            .filter(|(i, _)| permit.drop & (1 << i) != 0)
            .map(|(_, n)| *n)
            .collect();
        begin["drop_features"] = json!(names.join(","));
    }
    let req = c.send(begin)?;
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

/// What an update leaves of the history on this bridge, when it is not
/// kept: a bridge whose firmware predates the history (its `hello` has no
/// `history`) was installed with the partition table of before, which an
/// update cannot change; one whose history is off says why.
pub fn history_note(hello: &Hello<Read>) -> Option<String> {
    match hello.history.as_deref() {
        Some("recording") => None,
        Some(why) => Some(format!("note: no history on this bridge: {why}")),
        None => Some(
            "note: this bridge was installed before the history partition: the update works, \
             and the bridge runs without its history (events, days, capacity) until one \
             reinstall by cable (the browser installer's Update, or esptool: docs/updates.md)"
                .to_string(),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hello(history: Option<&str>) -> Hello<Read> {
        let mut v = serde_json::json!({"protocol":1,"firmware":"0.9.0","build":"b","chip":"esp32c3",
            "board":"ESP32-C3 SuperMini","features":["can"],"record_version":7,"read_only":false,
            "stream_period_ms":1000,"dropped_lines":0});
        if let Some(h) = history {
            v["history"] = serde_json::json!(h);
        }
        serde_json::from_value(v).unwrap()
    }

    #[test]
    fn an_update_says_when_the_bridge_keeps_no_history() {
        assert_eq!(history_note(&hello(Some("recording"))), None);
        let n = history_note(&hello(None)).unwrap();
        assert!(
            n.contains("installed before the history partition") && n.contains("reinstall"),
            "{n}"
        );
        let n = history_note(&hello(Some("the table predates it"))).unwrap();
        assert!(n.ends_with("the table predates it"), "{n}");
    }
}
