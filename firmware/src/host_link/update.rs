//! The `update_…` commands: the host link's side of [`crate::update`]. Every
//! one is answered with one `update` line saying where the transfer stands.

use base64::Engine as _;

use super::command::HostCommand;
use super::{encode, State};
use crate::update::file::Target;
use crate::update::transfer::{Answer, Ended, Phase, Version, CHUNK_MAX};
use crate::update::{Ota, Trial};
use crate::Instant;

/// "update to X rolled back: reason".
pub type RolledBack = heapless::String<112>;

/// The words of a rollback, as `hello`, `update` lines, the log and MQTT say
/// them.
pub fn rolled_back_text(ota: &Ota) -> Option<RolledBack> {
    let (version, cause) = ota.rolled_back()?;
    let mut s = RolledBack::new();
    for part in ["update to ", version, " rolled back: ", cause.words()] {
        let _ = s.push_str(part);
    }
    Some(s)
}

/// What `hello` says of updates: the slot running, its trial, the keys the
/// bridge trusts (public keys: the one built in, the owner's), and a
/// rollback.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct UpdateView {
    /// "update to X rolled back: reason".
    pub rolled_back: Option<RolledBack>,
    /// The app slot running (0: `ota_0`, 1: `ota_1`), when the bridge has two.
    pub slot: Option<u8>,
    /// On trial since boot.
    pub on_trial: bool,
    /// The key built into the image.
    pub built_in_key: Option<crate::update::file::Key>,
    /// The owner's key (`update_key`).
    pub owner_key: Option<crate::update::file::Key>,
}

/// What `hello` says of `ota`.
pub fn update_view(ota: &Ota) -> UpdateView {
    UpdateView {
        rolled_back: rolled_back_text(ota),
        slot: ota
            .layout()
            .map(|_| u8::try_from(ota.running_slot() % 2).unwrap_or(0)),
        on_trial: ota.trial() == Trial::OnTrial,
        built_in_key: crate::update::BUILT_IN_KEY,
        owner_key: ota.owner_key(),
    }
}

/// One `update` line's content (kept until its turn to be written).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct UpdateLine {
    state: &'static str,
    at: Option<u32>,
    phase: &'static str,
    size: Option<u32>,
    version: Option<Version>,
    ended: Option<Ended>,
    trial: &'static str,
}

impl UpdateLine {
    fn new(answer: Option<Answer>, ota: &Ota) -> Self {
        let (state, at) = match answer {
            None => ("status", None),
            Some(Answer::Next(at)) => ("next", Some(at)),
            Some(Answer::Busy(at)) => ("busy", Some(at)),
            Some(Answer::Acceptable) => ("acceptable", None),
            Some(Answer::Ended(_)) => ("ended", None),
            Some(Answer::BadChunk) => ("bad_chunk", None),
            Some(Answer::NotStarted) => ("not_started", None),
        };
        let t = ota.transfer();
        let (phase, size) = match t.phase() {
            Phase::Idle => ("idle", None),
            Phase::Receiving(_, size) => ("receiving", Some(size)),
            Phase::Finishing => ("finishing", None),
            Phase::Installed => ("installed", None),
        };
        let ended = match answer {
            Some(Answer::Ended(e)) => Some(e),
            _ => t.outcome(),
        };
        Self {
            state,
            at,
            phase,
            size,
            version: t.version().map(|v| {
                let mut s = Version::new();
                let _ = s.push_str(v);
                s
            }),
            ended,
            trial: match ota.trial() {
                Trial::Confirmed => "confirmed",
                Trial::OnTrial => "on_trial",
            },
        }
    }

    pub(super) fn encode(
        &self,
        req: Option<u32>,
        rolled_back: Option<&str>,
        out: &mut [u8],
    ) -> Option<usize> {
        encode::update(
            out,
            &super::schema::Update::<super::schema::Wire> {
                ty: "update",
                req,
                state: self.state,
                at: self.at,
                phase: self.phase,
                size: self.size,
                version: self.version.as_deref(),
                ended: self.ended.map(Ended::key),
                detail: self.ended.map(Ended::words),
                trial: self.trial,
                rolled_back,
            },
        )
    }
}

impl State {
    /// An `update_…` command; the line that answers it.
    pub(super) fn update(
        &self,
        now: Instant,
        command: &HostCommand<'_>,
        ota: &mut Ota,
    ) -> UpdateLine {
        let answer = match *command {
            HostCommand::UpdateBegin {
                size,
                permit,
                check,
            } => Some(ota.transfer_mut().begin(now, size, permit, check)),
            HostCommand::UpdateChunk { at, data } => {
                let mut buf = [0u8; CHUNK_MAX + 4];
                match base64::engine::general_purpose::STANDARD.decode_slice(data, &mut buf) {
                    Ok(n) => {
                        let me = Target {
                            chip: self.config.chip,
                            board: crate::boards::key_of(self.config.board),
                            version: self.config.firmware,
                            features: self.config.features.bits(),
                            slot_size: 0,
                        };
                        let keys = ota.keys();
                        let layout = ota.layout().copied();
                        let running = ota.running_slot();
                        let bytes = buf.get(..n).unwrap_or(&[]);
                        Some(ota.transfer_mut().chunk(
                            now,
                            at,
                            bytes,
                            &me,
                            &keys,
                            layout.as_ref(),
                            running,
                        ))
                    }
                    Err(_) => Some(Answer::BadChunk),
                }
            }
            HostCommand::UpdateCancel => Some(ota.transfer_mut().cancel()),
            _ => None,
        };
        UpdateLine::new(answer, ota)
    }
}
