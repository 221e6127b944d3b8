//! A host's side of the lines (`feature = "read-lines"`): owned text,
//! numbers as `f64`, and [`HostLine`], any line read back.

extern crate alloc;
use alloc::string::String;
use alloc::vec::Vec;

use super::*;

/// A host's side: owned text, numbers as `f64`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Read;

impl Form for Read {
    type Text = String;
    type Name = String;
    type Number = f64;
    type Cells = Vec<f64>;
    type Hex = String;
    type Names = Vec<String>;
    type Tag = ();
}

/// The form a host reads lines in (what the `Deserialize` of every line
/// asks of its form).
pub trait ReadSide:
    Form<
    Text = String,
    Name = String,
    Number = f64,
    Cells = Vec<f64>,
    Hex = String,
    Names = Vec<String>,
    Tag = (),
>
{
}

impl ReadSide for Read {}

/// Any line the bridge writes, by its `type`. A type this host does not
/// know (a newer bridge's) is [`HostLine::Other`], never an error.
#[derive(serde::Deserialize, Debug, Clone, PartialEq)]
#[serde(tag = "type", rename_all = "snake_case")]
#[allow(missing_docs)]
pub enum HostLine {
    Hello(Hello<Read>),
    Telemetry(Telemetry<Read>),
    Setting(SettingLine<Read>),
    SettingsEnd(End<Read>),
    EventsEnd(End<Read>),
    Statistics(StatisticsLine<Read>),
    Version(Version<Read>),
    Event(EventLine<Read>),
    Log(Log<Read>),
    Link(Link<Read>),
    Accepted(Accepted<Read>),
    Outcome(Outcome<Read>),
    ResetDone(ResetDone<Read>),
    Update(Update<Read>),
    Cleared(Cleared<Read>),
    Raw(Raw<Read>),
    Error(Error<Read>),
    Config(ConfigField<Read>),
    ConfigEnd(ConfigEnd<Read>),
    ConfigOutcome(ConfigOutcome<Read>),
    ConfigDone(ConfigDone<Read>),
    Battery(Battery<Read>),
    Pack(Pack<Read>),
    Can(CanLine<Read>),
    CanEnd(CanEnd<Read>),
    HistoryEvent(HistoryEvent<Read>),
    HistoryDay(HistoryDay<Read>),
    HistorySkipped(HistorySkipped<Read>),
    HistoryEnd(HistoryEnd<Read>),
    #[serde(other)]
    Other,
}

impl HostLine {
    /// The request id the line echoes, if any.
    pub fn req(&self) -> Option<u32> {
        match self {
            HostLine::Hello(l) => l.req,
            HostLine::Telemetry(l) => l.head.req,
            HostLine::Setting(l) => l.req,
            HostLine::SettingsEnd(l) | HostLine::EventsEnd(l) => l.req,
            HostLine::Can(l) => l.req,
            HostLine::CanEnd(l) => l.req,
            HostLine::HistoryEvent(l) => l.req,
            HostLine::HistoryDay(l) => l.req,
            HostLine::HistorySkipped(l) => l.req,
            HostLine::HistoryEnd(l) => l.req,
            HostLine::Statistics(l) => l.req,
            HostLine::Version(l) => l.req,
            HostLine::Event(l) => l.req,
            HostLine::Link(l) => l.req,
            HostLine::Accepted(l) => l.req,
            HostLine::Outcome(l) => l.req,
            HostLine::ResetDone(l) => l.req,
            HostLine::Update(l) => l.req,
            HostLine::Cleared(l) => l.req,
            HostLine::Error(l) => l.req,
            HostLine::Config(l) => l.req,
            HostLine::ConfigEnd(l) => l.req,
            HostLine::ConfigOutcome(l) => l.req,
            HostLine::ConfigDone(l) => l.req,
            HostLine::Log(_)
            | HostLine::Raw(_)
            | HostLine::Battery(_)
            | HostLine::Pack(_)
            | HostLine::Other => None,
        }
    }
}
