//! The parts an image may leave out. The host link (feature `host-link`)
//! and the inverter output (feature `can`) are in the station when the image
//! has the wire for them; without the feature their slot holds an
//! uninhabited stand-in, so `Option<NoHost>` is always `None`, takes no
//! memory, and the compiler removes every call on it (the bridge-only image
//! links neither part, as before the station).

#[cfg(not(all(feature = "host-link", feature = "can", feature = "net")))]
use crate::Instant;

/// The host link's slot.
#[cfg(feature = "host-link")]
pub type Host = crate::host_link::HostLink;
/// The host link's slot: none in this image.
#[cfg(not(feature = "host-link"))]
pub type Host = NoHost;

/// The inverter output's slot.
#[cfg(feature = "can")]
pub type Output = crate::inverter::Inverter;
/// The inverter output's slot: none in this image.
#[cfg(not(feature = "can"))]
pub type Output = NoOutput;

/// The update port's link (images with Wi-Fi: feature `net`; the desktop).
#[cfg(all(feature = "host-link", feature = "net"))]
pub type UpdatePort = crate::host_link::HostLink;
/// The update port's slot: none in this image (no network).
#[cfg(not(all(feature = "host-link", feature = "net")))]
pub type UpdatePort = NoPort;

/// No update port: a type without values.
#[cfg(not(all(feature = "host-link", feature = "net")))]
#[derive(Debug, Clone)]
pub enum NoPort {}

#[cfg(not(all(feature = "host-link", feature = "net")))]
#[allow(clippy::unused_self, missing_docs)]
impl NoPort {
    pub fn handle_rx(
        &mut self,
        _: Instant,
        _: &[u8],
        _: &mut crate::Bridge,
        _: &mut crate::config::state::ConfigState,
        _: &mut crate::update::Ota,
    ) {
        match *self {}
    }
    pub fn next_line(
        &mut self,
        _: Instant,
        _: &crate::Bridge,
        _: &crate::config::state::ConfigState,
        _: &mut [u8],
    ) -> Option<usize> {
        match *self {}
    }
    pub fn on_can_span(&mut self, _: Option<(u32, u32)>, _: &'static str) {
        match *self {}
    }
    pub fn can_wanted(&self) -> Option<u32> {
        match *self {}
    }
    pub fn on_can_entry(&mut self, _: u32, _: Option<crate::inverter::capture::Entry>) {
        match *self {}
    }
}

/// No host link: a type without values.
#[cfg(not(feature = "host-link"))]
#[derive(Debug, Clone)]
pub enum NoHost {}

#[cfg(not(feature = "host-link"))]
#[allow(clippy::unused_self, missing_docs)]
impl NoHost {
    pub fn connected(&mut self, _: Instant) {
        match *self {}
    }
    pub fn handle_rx(
        &mut self,
        _: Instant,
        _: &[u8],
        _: &mut crate::Bridge,
        _: &mut crate::config::state::ConfigState,
        _: &mut crate::update::Ota,
    ) {
        match *self {}
    }
    pub fn next_line(
        &mut self,
        _: Instant,
        _: &crate::Bridge,
        _: &crate::config::state::ConfigState,
        _: &mut [u8],
    ) -> Option<usize> {
        match *self {}
    }
    pub fn has_output(&self) -> bool {
        match *self {}
    }
    pub fn lines_dropped(&mut self, _: u32) {
        match *self {}
    }
    pub fn log(&mut self, _: crate::Level, _: &str) {
        match *self {}
    }
    pub fn boot_line(&mut self, _: crate::Level, _: &str) {
        match *self {}
    }
    pub fn capturing(&self) -> bool {
        match *self {}
    }
    pub fn on_uart_rx(&mut self, _: &[u8]) {
        match *self {}
    }
    pub fn on_uart_tx(&mut self, _: &[u8]) {
        match *self {}
    }
    pub fn on_report(&mut self, _: &crate::Report) {
        match *self {}
    }
    pub fn on_config_saved(
        &mut self,
        _: Result<crate::config::store::Saved, crate::config::store::StoreError>,
    ) {
        match *self {}
    }
    pub fn apply_config(&mut self, _: Instant, _: &crate::config::Config) {
        match *self {}
    }
    pub fn poll(&mut self, _: Instant, _: &crate::Bridge) -> Instant {
        match *self {}
    }
    pub fn on_battery(&mut self, _: Option<crate::inverter::packs::BatteryView>) {
        match *self {}
    }
    pub fn on_inverter(&mut self, _: Option<crate::host_link::encode::InverterState>) {
        match *self {}
    }
    pub fn on_can_span(&mut self, _: Option<(u32, u32)>, _: &'static str) {
        match *self {}
    }
    pub fn can_wanted(&self) -> Option<u32> {
        match *self {}
    }
    pub fn on_can_entry(&mut self, _: u32, _: Option<crate::inverter::capture::Entry>) {
        match *self {}
    }
    pub fn take_time(&mut self) -> Option<u32> {
        match *self {}
    }
    pub fn on_history(&mut self, _: Option<&'static str>) {
        match *self {}
    }
    pub fn history_start(&mut self) -> bool {
        match *self {}
    }
    pub fn history_wanted(&self) -> bool {
        match *self {}
    }
    pub fn on_history_item(&mut self, _: Option<crate::history::log::Listed>) {
        match *self {}
    }
    pub fn on_restart_pending(&mut self, _: u32) {
        match *self {}
    }
    pub fn on_mqtt(&mut self, _: &'static str) {
        match *self {}
    }
    pub fn on_radio(&mut self, _: crate::wifi::Radio) {
        match *self {}
    }
    pub fn improv(&self) -> &crate::improv::Improv {
        match *self {}
    }
    pub fn improv_mut(&mut self) -> &mut crate::improv::Improv {
        match *self {}
    }
    pub fn wifi_link(&mut self, _: crate::improv::WifiLink) {
        match *self {}
    }
}

/// No inverter output: a type without values.
#[cfg(not(feature = "can"))]
#[derive(Debug, Clone)]
pub enum NoOutput {}

#[cfg(not(feature = "can"))]
#[allow(clippy::unused_self, missing_docs)]
impl NoOutput {
    pub fn on_snapshot(
        &mut self,
        _: Instant,
        _: &protocol_core::views::LiveSnapshot,
        _: Option<crate::inverter::control::PackSettings>,
        _: Option<&protocol_core::views::VersionInfo>,
    ) {
        match *self {}
    }
    pub fn on_event(&mut self, _: &protocol_core::events::Event) {
        match *self {}
    }
    pub fn on_received(&mut self, _: Instant, _: u16, _: &[u8]) {
        match *self {}
    }
    pub fn on_tx(&mut self, _: Instant, _: crate::inverter::TxResult) {
        match *self {}
    }
    pub fn on_bus_off(&mut self, _: Instant) {
        match *self {}
    }
    pub fn poll(&mut self, _: Instant) -> crate::inverter::InverterAction {
        match *self {}
    }
    pub fn reconfigure(&mut self, _: crate::inverter::InverterConfig) {
        match *self {}
    }
    pub fn limits_sent(&self, _: Instant) -> Option<crate::inverter::control::Limits> {
        match *self {}
    }
    pub fn can_state(&self) -> crate::inverter::CanState {
        match *self {}
    }
    pub fn inverter_heard(&self) -> bool {
        match *self {}
    }
    pub fn protection(&self) -> Option<crate::inverter::dialect::Stops> {
        match *self {}
    }
    pub fn told(&self) -> Option<crate::inverter::dialect::Told> {
        match *self {}
    }
    pub fn ignored(&self) -> Option<crate::inverter::ignored::Ignored> {
        match *self {}
    }
    pub fn stage(&self) -> Option<crate::inverter::finish::Stage> {
        match *self {}
    }
    pub fn reasons(&self) -> Option<crate::inverter::why::Reasons> {
        match *self {}
    }
    pub fn doctor(&self) -> &crate::inverter::doctor::Doctor {
        match *self {}
    }
    pub fn capture(&self) -> &crate::inverter::capture::Capture {
        match *self {}
    }
    pub fn next_report(&mut self) -> Option<crate::inverter::InverterReport> {
        match *self {}
    }
    pub fn node(&self) -> u8 {
        match *self {}
    }
    pub fn battery_view(&self, _: Instant) -> Option<crate::inverter::packs::BatteryView> {
        match *self {}
    }
    pub fn config(&self) -> &crate::inverter::InverterConfig {
        match *self {}
    }
}
