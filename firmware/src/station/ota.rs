//! The station's side of updates ([`crate::update`]): the flash work of a
//! transfer and of the trial's confirmation, each done only while no BMS
//! reply can be on its way (like a save of the record), the trial's watch,
//! the restart into an installed image, and what the log says of them.

use super::{Action, Logged, Station};
use crate::inverter::CanState;
use crate::text::Line;
use crate::update::otadata::Cause;
use crate::update::transfer::{Ended, Op, Version};
use crate::update::{Done, Ota, Trial};
use crate::{Instant, Level};

/// After an update is installed, the bridge restarts this much later (the
/// host link's answer goes out first).
pub const RESTART_DELAY_US: Instant = crate::SECOND;

/// An update's flash operation waits for a gap this long before the BMS
/// poll's next request and the CAN output's next frame: a sector's erase
/// (about 45 ms on the boards' flash) or program (about 15 ms) stops the CPU,
/// and in such a gap it delays neither.
pub const FLASH_WINDOW_US: Instant = 100 * crate::MS;

/// What the log says of updates.
#[derive(Debug, Clone, PartialEq)]
pub enum UpdateNote {
    /// This image came back from an update that failed its trial.
    RolledBack(Version, Cause),
    /// This image runs on trial.
    OnTrial,
    /// It confirmed itself.
    Confirmed,
    /// The confirmation could not be written (tried again at the next boot).
    ConfirmFailed,
    /// A transfer ended without an update.
    Ended(Ended),
    /// An update is installed: the bridge restarts into it.
    Installed(Version),
}

impl UpdateNote {
    /// The level it is logged at.
    pub fn level(&self) -> Level {
        match self {
            Self::OnTrial | Self::Confirmed | Self::Installed(_) => Level::Info,
            Self::Ended(Ended::Cancelled) => Level::Info,
            _ => Level::Warn,
        }
    }

    /// The words.
    pub fn text(&self, out: &mut Line) {
        match self {
            Self::RolledBack(v, c) => {
                out.push("update to ")
                    .push(v)
                    .push(" rolled back: ")
                    .push(c.words());
            }
            Self::OnTrial => {
                out.push(
                    "update: this image runs on trial; it confirms itself once BMS data and the \
                     inverter output run (at the latest after 10 min without a reset)",
                );
            }
            Self::Confirmed => {
                out.push("update: this image confirmed itself");
            }
            Self::ConfirmFailed => {
                out.push("update: the confirmation could not be written to otadata");
            }
            Self::Ended(e) => {
                out.push("update abandoned: ").push(e.words());
            }
            Self::Installed(v) => {
                out.push("update to ")
                    .push(v)
                    .push(" installed: restarting into it (on trial)");
            }
        }
    }
}

impl Station {
    /// Where the slots are and what `otadata` says, after the boot's own
    /// write ([`crate::update::start`]); the owner's key comes from the
    /// record.
    pub fn set_ota(&mut self, mut ota: Ota) {
        ota.set_owner_key(self.config.running().update_key());
        if let Some((v, c)) = ota.rolled_back() {
            let mut s = Version::new();
            let _ = s.push_str(v);
            let _ = self.ota_notes.push_back(UpdateNote::RolledBack(s, c));
        }
        if ota.trial() == Trial::OnTrial {
            let _ = self.ota_notes.push_back(UpdateNote::OnTrial);
        }
        #[cfg(feature = "host-link")]
        if let Some(h) = self.host.as_mut() {
            h.set_update(crate::host_link::update_view(&ota));
        }
        self.ota = ota;
    }

    /// The update side.
    pub fn ota(&self) -> &Ota {
        &self.ota
    }

    /// The bytes of an [`Op::Program`].
    pub fn program_bytes(&self) -> &[u8] {
        self.ota.transfer().program_bytes()
    }

    /// The shell did [`Action::Flash`]: `ok` when it worked and read back
    /// the same.
    pub fn flashed(&mut self, now: Instant, ok: bool) {
        let note = match self.ota.op_done(ok) {
            Done::Nothing => None,
            Done::Confirmed => Some(UpdateNote::Confirmed),
            Done::ConfirmFailed => Some(UpdateNote::ConfirmFailed),
            Done::Ended(e) => Some(UpdateNote::Ended(e)),
            Done::Installed => {
                self.restart_at = Some(now + RESTART_DELAY_US);
                let mut v = Version::new();
                let _ = v.push_str(self.ota.transfer().version().unwrap_or("?"));
                Some(UpdateNote::Installed(v))
            }
        };
        if let Some(n) = note {
            self.generation = self.generation.wrapping_add(1);
            let _ = self.ota_notes.push_back(n);
            // A trial that confirmed itself (or could not) is what `hello`
            // says from now on, on USB and on the update port.
            self.refresh_update_view();
        }
    }

    /// The host link's and the update port's view of the update side
    /// (`hello`'s `update`) made again from [`Ota`]: after anything that
    /// changes the slot, the trial or the keys.
    pub(super) fn refresh_update_view(&mut self) {
        #[cfg(feature = "host-link")]
        {
            let view = crate::host_link::update_view(&self.ota);
            if let Some(h) = self.host.as_mut() {
                h.set_update(view.clone());
            }
            #[cfg(feature = "net")]
            if let Some(u) = self.update_port.as_mut() {
                u.set_update(view);
            }
            #[cfg(not(feature = "net"))]
            let _ = view;
        }
    }

    /// The update's work in [`Station::poll`] while the BMS link is quiet
    /// and nothing else is due before `free_until`: a restart that is due, a
    /// flash operation when the gap is [`FLASH_WINDOW_US`] long.
    pub(super) fn ota_action(&mut self, now: Instant, free_until: Instant) -> Option<Action> {
        if let Some(e) = self.ota.transfer_mut().poll(now) {
            let _ = self.ota_notes.push_back(UpdateNote::Ended(e));
        }
        let t = self.bridge.telemetry();
        let worked = t.snapshot_seq > 0
            && self
                .inverter
                .as_ref()
                .is_none_or(|i| matches!(i.can_state(), CanState::Running | CanState::Off));
        self.ota.tick(now, worked);
        if self.restart_at.is_some_and(|t| now >= t) {
            return Some(Action::Restart);
        }
        if free_until >= now.saturating_add(FLASH_WINDOW_US) {
            if let Some(op) = self.ota.next_op() {
                return Some(Action::Flash(op));
            }
        }
        None
    }

    /// When the update side wants to be polled again.
    pub(super) fn ota_wake(&self, now: Instant) -> Instant {
        let mut wake = self.restart_at.unwrap_or(Instant::MAX);
        if self.ota.trial() == Trial::OnTrial || self.ota.next_op().is_some() {
            wake = wake.min(now + crate::SECOND);
        }
        if !matches!(
            self.ota.transfer().phase(),
            crate::update::transfer::Phase::Idle
        ) {
            wake = wake.min(now + crate::SECOND);
        }
        wake
    }

    /// A connection came to the update port on the network
    /// ([`crate::update::TCP_PORT`]; images with Wi-Fi): a link of its own,
    /// which takes `hello` and the `update_…` commands only. A second
    /// connection replaces the first.
    pub fn update_port_connected(&mut self, now: Instant) {
        #[cfg(all(feature = "host-link", feature = "net"))]
        {
            let config = self.config.running().host_link(&self.identity);
            let mut link = crate::host_link::HostLink::update_port(config, now);
            link.set_update(crate::host_link::update_view(&self.ota));
            link.connected(now);
            self.update_port = Some(link);
        }
        #[cfg(not(all(feature = "host-link", feature = "net")))]
        let _ = now;
    }

    /// The connection to the update port closed.
    pub fn update_port_closed(&mut self) {
        self.update_port = None;
    }

    /// Bytes from the update port's connection.
    pub fn update_port_rx(&mut self, now: Instant, bytes: &[u8]) {
        self.watch.who = Some(crate::history::event::Who::Network);
        if let Some(l) = self.update_port.as_mut() {
            l.handle_rx(
                now,
                bytes,
                &mut self.bridge,
                &mut self.config,
                &mut self.ota,
            );
        }
    }

    /// The next line for the update port's connection (`\n`-terminated).
    pub fn next_update_port_line(&mut self, now: Instant, out: &mut [u8]) -> Option<usize> {
        let l = self.update_port.as_mut()?;
        feed_capture!(l, self.inverter.as_ref());
        l.next_line(now, &self.bridge, &self.config, out)
    }

    /// Hands the update port's writer every line there is room for, each
    /// whole (as [`Station::hand_out_host_lines`]); a line that does not fit
    /// whole is dropped (the sender asks again). Returns the lines handed.
    pub fn hand_out_update_port_lines(
        &mut self,
        now: Instant,
        queue: &mut impl crate::host_link::queue::ByteQueue,
        buf: &mut [u8; crate::host_link::OUT_LINE_MAX],
    ) -> u32 {
        super::pumps::hand_out(queue, buf, |b| self.next_update_port_line(now, b)).0
    }

    /// The next update note to log.
    pub(super) fn next_update_note(&mut self) -> Option<Logged> {
        self.ota_notes.pop_front().map(Logged::Update)
    }
}

/// An [`Op`] as the log and tests name it.
pub fn op_name(op: &Op) -> &'static str {
    match op {
        Op::Erase(_) => "erase",
        Op::Program(_) => "program",
        Op::Otadata(_) => "otadata",
    }
}
