//! The configuration a running bridge holds: the record it runs with and the
//! record it will store, how a change by name becomes one outcome per field,
//! and when the flash may be written.
//!
//! Two records:
//! * **running** — what the bridge runs with now: the record it started with,
//!   plus every change of a field that applies at once ([`Applies::Now`]);
//! * **stored** — the newest record: what flash holds, or will hold once the
//!   pending save is done. A field that applies at the next restart differs
//!   between the two until then ([`ConfigState::restart_pending`]).
//!
//! A change is all or nothing: every field is checked (name, kind, range), then
//! the new record as a whole ([`Config::validate`], and against the BMS's own
//! settings when they are known); one refusal and nothing changes. Changes are
//! saved to flash later, when the chip shell finds the BMS link quiet
//! ([`ConfigState::save_due`] and [`crate::Bridge::quiet`]).

use heapless::{Deque, Vec};

use super::store::{Saved, Source, StoreError, StoreSite};
use super::value::{FieldError, Parsed};
use super::{Applies, Config, FieldId, PackSettings, RuleError, FIELDS};

/// Most fields in one change.
pub const MAX_CHANGES: usize = 12;

/// What happened to one field of a change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Outcome {
    /// Changed, and the bridge runs with it now.
    Applied,
    /// Changed in the stored record; the bridge runs with it after a restart.
    AtRestart,
    /// The record already held this value.
    Unchanged,
    /// Refused: not a value of this field, or out of its range.
    Refused(FieldError),
    /// Refused: the record would break a rule between fields, or one against
    /// the BMS's settings; then the values the field may take (raw).
    RuleBroken(&'static str, Option<(i32, i32)>),
    /// Not applied, because another field of the change was refused.
    NotApplied,
}

impl Outcome {
    /// As the host link prints it.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Applied => "applied",
            Self::AtRestart => "at_restart",
            Self::Unchanged => "unchanged",
            Self::Refused(_) | Self::RuleBroken(..) => "refused",
            Self::NotApplied => "not_applied",
        }
    }
}

/// One field's outcome.
pub type FieldOutcome = (FieldId, Outcome);

/// Outcomes of one change (one per field named, plus the field of a broken
/// rule when it was not named).
pub type Outcomes = Vec<FieldOutcome, { MAX_CHANGES + 1 }>;

/// What the log says about the configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Note {
    /// The record the bridge started with, and where from.
    Loaded(Source),
    /// A field changed (its new value is in the stored record).
    Changed(FieldId, Applies),
    /// Every field went back to its default.
    Reset,
    /// Read-only was lifted by the BOOT button.
    Unlocked,
    /// The stored record was saved (or found unchanged).
    Saved(Saved),
    /// Saving failed: the change stays in RAM and is tried again.
    SaveFailed(StoreError),
}

/// Attempts of a save before the change is only kept in RAM.
pub const SAVE_ATTEMPTS: u8 = 3;

/// See the module documentation.
#[derive(Debug, Clone)]
pub struct ConfigState {
    running: Config,
    stored: Config,
    source: Source,
    /// A save is wanted (attempts left).
    save: Option<u8>,
    /// At-once fields changed since [`ConfigState::take_running_change`].
    running_changed: bool,
    notes: Deque<Note, 8>,
    site: Option<StoreSite>,
}

impl ConfigState {
    /// Starts with the record loaded at start-up.
    pub fn new(config: Config, source: Source) -> Self {
        let mut notes = Deque::new();
        let _ = notes.push_back(Note::Loaded(source));
        Self {
            running: config.clone(),
            stored: config,
            source,
            save: None,
            running_changed: false,
            notes,
            site: None,
        }
    }

    /// Starts with a record the program that runs the bridge chose itself
    /// (the desktop tool's direct mode: no bridge of its own, nothing
    /// stored): the log says nothing about a configuration, since the owner
    /// set none.
    pub fn fixed(config: Config) -> Self {
        let mut s = Self::new(config, Source::Empty);
        s.notes.clear();
        s
    }

    /// Where the store lives (the chip's flash, its partition): the log and
    /// `hello` name it.
    pub fn set_site(&mut self, site: StoreSite) {
        self.site = Some(site);
    }

    /// Where the store lives, when the shell said.
    pub fn site(&self) -> Option<StoreSite> {
        self.site
    }

    /// What the bridge runs with.
    pub fn running(&self) -> &Config {
        &self.running
    }

    /// The newest record (stored, or to be stored).
    pub fn stored(&self) -> &Config {
        &self.stored
    }

    /// Where the start-up record came from.
    pub fn source(&self) -> Source {
        self.source
    }

    /// True when `id` has a stored value the bridge runs with only after a restart.
    pub fn restart_pending(&self, id: FieldId) -> bool {
        self.running.get(id) != self.stored.get(id)
    }

    /// Fields waiting for a restart.
    pub fn restarts_pending(&self) -> usize {
        FIELDS.iter().filter(|f| self.restart_pending(f.id)).count()
    }

    /// True when a save is waiting.
    pub fn save_due(&self) -> bool {
        self.save.is_some()
    }

    /// The running record's at-once fields changed since the last call: the new
    /// running record (for the tasks that apply them: the inverter output).
    pub fn take_running_change(&mut self) -> Option<&Config> {
        core::mem::take(&mut self.running_changed).then_some(&self.running)
    }

    /// The next line for the log.
    pub fn next_note(&mut self) -> Option<Note> {
        self.notes.pop_front()
    }

    fn note(&mut self, n: Note) {
        if self.notes.is_full() {
            self.notes.pop_front();
        }
        let _ = self.notes.push_back(n);
    }

    /// Applies a change: every field checked, then the record as a whole
    /// (against the BMS's settings when known). All or nothing; one outcome per
    /// field. `refused` lists fields already refused by the caller (an unknown
    /// name, text that did not parse): then nothing is applied either.
    pub fn change(
        &mut self,
        changes: &[(FieldId, Parsed)],
        refused: bool,
        bms: Option<&PackSettings>,
    ) -> Outcomes {
        let mut out = Outcomes::new();
        let mut next = self.stored.clone();
        let mut failed = refused;
        let mut results: Vec<Option<Outcome>, MAX_CHANGES> = Vec::new();
        for (i, (id, v)) in changes.iter().enumerate() {
            let twice = changes
                .get(..i)
                .is_some_and(|b| b.iter().any(|(o, _)| o == id));
            let r = if twice {
                Some(Outcome::Refused(FieldError {
                    out_of_range: false,
                    detail: "named twice",
                }))
            } else {
                next.set(*id, v.as_value()).err().map(Outcome::Refused)
            };
            failed |= r.is_some();
            let _ = results.push(r);
        }
        let rule = if failed {
            None
        } else {
            match bms {
                Some(b) => next.validate_with_bms(b),
                None => next.validate(),
            }
            .err()
        };
        if failed || rule.is_some() {
            for ((id, _), r) in changes.iter().zip(results.iter()) {
                let o = match (r, rule) {
                    (Some(o), _) => *o,
                    (
                        None,
                        Some(RuleError {
                            field,
                            detail,
                            allowed,
                        }),
                    ) if field == *id => Outcome::RuleBroken(detail, allowed),
                    _ => Outcome::NotApplied,
                };
                let _ = out.push((*id, o));
            }
            if let Some(RuleError {
                field,
                detail,
                allowed,
            }) = rule
            {
                if !changes.iter().any(|(id, _)| *id == field) {
                    let _ = out.push((field, Outcome::RuleBroken(detail, allowed)));
                }
            }
            return out;
        }
        for (id, _) in changes {
            let _ = out.push((*id, self.outcome_of(*id, &next)));
        }
        self.commit(next);
        out
    }

    /// What changing `id` to its value in `next` does.
    fn outcome_of(&self, id: FieldId, next: &Config) -> Outcome {
        if next.get(id) == self.stored.get(id) {
            Outcome::Unchanged
        } else if id.field().applies == Applies::Now || next.get(id) == self.running.get(id) {
            Outcome::Applied
        } else {
            Outcome::AtRestart
        }
    }

    /// `next` becomes the stored record; its at-once fields run now.
    fn commit(&mut self, next: Config) {
        let mut changed_now = false;
        for f in FIELDS {
            if next.get(f.id) != self.stored.get(f.id) {
                let applies =
                    if f.applies == Applies::Now || next.get(f.id) == self.running.get(f.id) {
                        Applies::Now
                    } else {
                        Applies::Restart
                    };
                changed_now |= f.applies == Applies::Now;
                self.note(Note::Changed(f.id, applies));
            }
        }
        if next == self.stored {
            return;
        }
        self.running.take_immediate(&next);
        self.running_changed |= changed_now;
        self.stored = next;
        self.save = Some(SAVE_ATTEMPTS);
    }

    /// Every field back to its default: one outcome per field that changes.
    pub fn reset(&mut self) -> Vec<FieldOutcome, { FIELDS.len() }> {
        let next = Config::default();
        let mut out = Vec::new();
        for f in FIELDS {
            let o = self.outcome_of(f.id, &next);
            if o != Outcome::Unchanged {
                let _ = out.push((f.id, o));
            }
        }
        self.note(Note::Reset);
        self.commit(next);
        out
    }

    /// The Wi-Fi side joined this network with this key (Improv Wi-Fi): the
    /// bridge runs with them now, and they are stored. Not read-only-checked:
    /// the owner typed them at the device, as with the BOOT button. False
    /// when the record would not take them (nothing changes then).
    pub fn joined_network(&mut self, ssid: &str, key: &str) -> bool {
        let mut next = self.stored.clone();
        if next
            .set(FieldId::WifiSsid, super::Value::Text(ssid))
            .is_err()
            || next.set(FieldId::WifiKey, super::Value::Text(key)).is_err()
            || next.validate().is_err()
        {
            return false;
        }
        for id in [FieldId::WifiSsid, FieldId::WifiKey] {
            if next.get(id) != self.stored.get(id) {
                self.note(Note::Changed(id, Applies::Now));
            }
        }
        let _ = self
            .running
            .set(FieldId::WifiSsid, super::Value::Text(ssid));
        let _ = self.running.set(FieldId::WifiKey, super::Value::Text(key));
        if next != self.stored {
            self.stored = next;
            self.save = Some(SAVE_ATTEMPTS);
        }
        true
    }

    /// The BOOT button was held: read-only is lifted, now and in flash.
    pub fn unlock(&mut self) {
        self.note(Note::Unlocked);
        if self.stored.read_only || self.running.read_only {
            let mut next = self.stored.clone();
            next.read_only = false;
            self.running.read_only = false;
            self.running_changed = true;
            self.commit(next);
        }
    }

    /// What the save of [`ConfigState::stored`] did. A failure is tried again
    /// (at most [`SAVE_ATTEMPTS`] times in all); the change stays in RAM.
    /// Returns the final result once there is one (saved, or the last attempt
    /// failed): what the host that asked for the change is told.
    pub fn saved(
        &mut self,
        result: Result<Saved, StoreError>,
    ) -> Option<Result<Saved, StoreError>> {
        match result {
            Ok(s) => {
                self.save = None;
                self.note(Note::Saved(s));
                Some(Ok(s))
            }
            Err(e) => {
                self.note(Note::SaveFailed(e));
                match self.save {
                    Some(n) if n > 1 => {
                        self.save = Some(n - 1);
                        None
                    }
                    _ => {
                        self.save = None;
                        Some(Err(e))
                    }
                }
            }
        }
    }
}
