//! The configuration commands of the host link: `set_config` (every field
//! parsed before any is changed; one `config_outcome` per field) and
//! `reset_config`'s end, with the `config_done` line sent now or, when the
//! record must be saved, after the save ([`super::HostLink::on_config_saved`]).

use heapless::{String, Vec};

use super::subject;
use super::{command, ErrorCode, Out, State, QUEUE, SUBJECT_MAX};
use crate::bridge::Bridge;
use crate::config::state::{ConfigState, Outcome};
use crate::config::store::{Saved, StoreError};
use crate::config::value::{self, FieldError, Parsed};
use crate::config::{FieldId, PackSettings, TEXT_MAX};
use crate::Instant;

/// What a `config_outcome` line says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum ConfigAnswer {
    /// A field the record has.
    Field(FieldId, Outcome),
    /// A name no field has.
    Unknown,
    /// Text that is not a value of the field.
    Invalid(FieldId, FieldError),
}

/// What a `config_done` line says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConfigDone {
    /// Echoed request id.
    pub req: Option<u32>,
    /// Fields changed.
    pub changed: u8,
    /// The save: `None` when nothing needed saving.
    pub saved: Option<Result<Saved, StoreError>>,
    /// Fields waiting for a restart.
    pub restart_needed: u8,
}

/// `set_config`s whose `config_done` waits for the flash.
pub const PENDING_CONFIG: usize = 4;

impl State {
    /// After a change of `changed` fields: the running record applied here,
    /// and the `config_done` line now (nothing to save) or after the save.
    pub(super) fn config_changed(
        &mut self,
        now: Instant,
        req: Option<u32>,
        changed: u8,
        config: &ConfigState,
    ) {
        self.apply_config(now, config.running());
        let done = ConfigDone {
            req,
            changed,
            saved: None,
            restart_needed: config.restarts_pending() as u8,
        };
        if config.save_due() {
            if self.config_saves.push(done).is_err() {
                // Checked before the change: never full here.
                self.report(Out::ConfigDone(done));
            }
        } else {
            self.report(Out::ConfigDone(done));
        }
    }

    pub(super) fn set_config(
        &mut self,
        now: Instant,
        req: Option<u32>,
        fields: &[(&str, serde_json_core::str::EscapedStr<'_>)],
        bridge: &Bridge,
        config: &mut ConfigState,
    ) {
        // Every line this command will write must fit: accepted, one outcome
        // per field (and one for a broken rule), done.
        if self.config_saves.is_full() || self.queue.len() + fields.len() + 3 > QUEUE {
            return self.error(req, ErrorCode::Busy, "configuration changes pending", "");
        }
        let mut parsed: Vec<(FieldId, Parsed), { command::MAX_SET_CONFIG }> = Vec::new();
        let mut answers: Vec<
            (String<SUBJECT_MAX>, Option<ConfigAnswer>),
            { command::MAX_SET_CONFIG },
        > = Vec::new();
        for (name, text) in fields {
            let answer = match FieldId::from_name(name) {
                None => Some(ConfigAnswer::Unknown),
                // An image without Wi-Fi has no use for a network field: it
                // is refused rather than kept where nothing reads it.
                Some(id)
                    if id.field().group == crate::config::Group::Network
                        && !self.config.features.wifi =>
                {
                    Some(ConfigAnswer::Invalid(
                        id,
                        FieldError {
                            out_of_range: false,
                            detail:
                                "this image has no Wi-Fi: a network field would do \
                                     nothing (the images with Wi-Fi end in -wifi: docs/flashing.md)",
                        },
                    ))
                }
                Some(id) => match unescape(text)
                    .and_then(|t| value::parse(id.field(), &t))
                    .or_else(|e| {
                        // Too long to hold: a key says what it is first (a
                        // private key is longer than a public one), and a
                        // public key written with spaces is its 64 digits.
                        match id.field().kind {
                            crate::config::Kind::Text {
                                rule: crate::config::TextRule::Key,
                                ..
                            } if e == FieldError::TOO_LONG => value::parse(id.field(), text.0),
                            _ => Err(e),
                        }
                    })
                    .map_err(|e| (id, e))
                {
                    Ok(p) => {
                        let _ = parsed.push((id, p));
                        None
                    }
                    Err((id, e)) => Some(ConfigAnswer::Invalid(id, e)),
                },
            };
            let _ = answers.push((subject(name), answer));
        }
        self.push(Out::Accepted(req, "set_config"));
        let refused = answers.iter().any(|(_, a)| a.is_some());
        if refused {
            for (name, a) in answers {
                let outcome = match a {
                    Some(a) => a,
                    None => match FieldId::from_name(&name) {
                        Some(id) => ConfigAnswer::Field(id, Outcome::NotApplied),
                        None => ConfigAnswer::Unknown,
                    },
                };
                self.report(Out::ConfigOutcome { req, name, outcome });
            }
            return self.config_changed(now, req, 0, config);
        }
        let bms = bridge
            .telemetry()
            .settings
            .as_ref()
            .and_then(PackSettings::from_registers);
        let outcomes = config.change(&parsed, false, bms.as_ref());
        let mut changed = 0u8;
        for (id, o) in outcomes {
            if matches!(o, Outcome::Applied | Outcome::AtRestart) {
                changed = changed.saturating_add(1);
            }
            self.report(Out::ConfigOutcome {
                req,
                name: subject(id.name()),
                outcome: ConfigAnswer::Field(id, o),
            });
        }
        self.config_changed(now, req, changed, config);
    }
}

/// The text of a JSON string with its escapes resolved.
fn unescape(s: &serde_json_core::str::EscapedStr<'_>) -> Result<String<TEXT_MAX>, FieldError> {
    use serde_json_core::str::EscapedStringFragment as F;
    let mut out = String::new();
    for fragment in s.fragments() {
        let ok = match fragment {
            Ok(F::NotEscaped(t)) => out.push_str(t).is_ok(),
            Ok(F::Escaped(c)) => out.push(c).is_ok(),
            Err(_) => {
                return Err(FieldError {
                    out_of_range: false,
                    detail: "invalid escape in the string",
                })
            }
        };
        if !ok {
            return Err(FieldError::TOO_LONG);
        }
    }
    Ok(out)
}
