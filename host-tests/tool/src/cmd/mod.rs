//! One module per `tinybms` subcommand: each turns its arguments into calls
//! of the client ([`super::client`]) and prints what they give (with the
//! helpers of [`super::monitor`], [`super::settings`], [`super::config`]).
//! What several share (connecting, confirmations, writing settings) is in
//! [`super`].

pub mod apply;
pub mod clear;
pub mod config;
pub mod doctor;
pub mod events;
pub mod history;
pub mod log;
pub mod monitor;
pub mod mqtt;
pub mod ports;
pub mod record;
pub mod set;
pub mod settings;
pub mod show;
pub mod update;
pub mod wifi;
