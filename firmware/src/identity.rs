//! Who the bridge is: the firmware's version and build, the board and chip it
//! runs on, what is built into the image, and the version of the
//! configuration record it writes. In the host link's `hello` and the log.

/// This firmware's version: `TINYBMS_VERSION` when it was built (a release
/// sets it to its tag without the `v`, the ready-made images and their
/// installer manifests carry the same), else the package's.
pub const FIRMWARE: &str = match option_env!("TINYBMS_VERSION") {
    Some(v) => v,
    None => env!("CARGO_PKG_VERSION"),
};

/// What it was built from: `TINYBMS_BUILD` when it was built (the ready-made
/// images and releases set it to the commit or tag), else `dev`.
pub const BUILD: &str = match option_env!("TINYBMS_BUILD") {
    Some(b) => b,
    None => "dev",
};

/// What is built into an image, by the cargo feature's name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Features {
    /// The inverter output over CAN (`can`).
    pub can: bool,
    /// The host link on USB (`host-link`).
    pub host_link: bool,
    /// Wi-Fi and MQTT (`wifi`).
    pub wifi: bool,
    /// The configuration record in flash (`store`).
    pub store: bool,
}

impl Features {
    /// The names of those built in, in a fixed order.
    pub fn names(&self) -> heapless::Vec<&'static str, 4> {
        let mut v = heapless::Vec::new();
        for (on, name) in [
            (self.can, "can"),
            (self.host_link, "host-link"),
            (self.wifi, "wifi"),
            (self.store, "store"),
        ] {
            if on {
                let _ = v.push(name);
            }
        }
        v
    }
}

/// The bridge's identity.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Identity {
    /// The chip (`esp32c3`, `esp32c6`; `sim` on the desk).
    pub chip: &'static str,
    /// The board (its name in the board table; `simulated` on the desk).
    pub board: &'static str,
    /// What is built in.
    pub features: Features,
    /// The firmware's version ([`FIRMWARE`]; on the desk, the image booted).
    pub firmware: &'static str,
}

impl Identity {
    /// On the desk: `chip`, a simulated board, what the runner attaches.
    pub const fn desktop(chip: &'static str, features: Features) -> Self {
        Self {
            chip,
            board: "simulated",
            features,
            firmware: FIRMWARE,
        }
    }
}
