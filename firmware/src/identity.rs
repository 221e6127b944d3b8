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

/// The features an image can have, by name, in a fixed order: bit n of
/// [`Features::bits`] is the n-th (an update file names them too).
pub const FEATURE_NAMES: [&str; 4] = ["can", "host-link", "wifi", "store"];

impl Features {
    /// Built in or not, in the order of [`FEATURE_NAMES`].
    const fn flags(self) -> [bool; 4] {
        [self.can, self.host_link, self.wifi, self.store]
    }

    /// The names of those built in, in a fixed order.
    pub fn names(&self) -> heapless::Vec<&'static str, 4> {
        let mut v = heapless::Vec::new();
        for (on, name) in self.flags().into_iter().zip(FEATURE_NAMES) {
            if on {
                let _ = v.push(name);
            }
        }
        v
    }
}

/// What precedes the features' names in an image ([`Features::tag`]), so
/// that `tinybms sign` finds them in the image's bytes.
pub const FEATURES_MARK: &[u8] = b"tinybms-features=";

/// The length of [`Features::tag`].
pub const FEATURES_TAG_LEN: usize = 48;

impl Features {
    /// The bits of [`FEATURE_NAMES`] built in.
    pub fn bits(self) -> u8 {
        (0u8..)
            .zip(self.flags())
            .fold(0, |bits, (i, on)| bits | u8::from(on) << i)
    }

    /// `tinybms-features=can,host-link,wifi,store` (the names built in), then
    /// zeros: kept in the image so that an update file's header names the
    /// image's own features.
    // A const fn cannot use `get`: every index is below the array's length
    // (the mark and the longest list, 41 bytes, fit in 48).
    #[allow(clippy::indexing_slicing)]
    pub const fn tag(self) -> [u8; FEATURES_TAG_LEN] {
        let mut out = [0u8; FEATURES_TAG_LEN];
        let mut n = 0;
        let mut i = 0;
        while i < FEATURES_MARK.len() {
            out[n] = FEATURES_MARK[i];
            n += 1;
            i += 1;
        }
        let flags = self.flags();
        let mut first = true;
        let mut k = 0;
        while k < flags.len() {
            let name = FEATURE_NAMES[k].as_bytes();
            if flags[k] {
                if !first {
                    out[n] = b',';
                    n += 1;
                }
                first = false;
                let mut j = 0;
                while j < name.len() {
                    out[n] = name[j];
                    n += 1;
                    j += 1;
                }
            }
            k += 1;
        }
        out
    }
}

/// The features an image names in its bytes ([`Features::tag`]), if it
/// names them: the names after the mark, up to the first zero.
pub fn features_in_image(image: &[u8]) -> Option<&str> {
    let at = image
        .windows(FEATURES_MARK.len())
        .position(|w| w == FEATURES_MARK)?;
    let rest = image.get(at + FEATURES_MARK.len()..)?;
    let end = rest.iter().position(|&b| b == 0)?;
    let names = core::str::from_utf8(rest.get(..end)?).ok()?;
    names
        .bytes()
        .all(|b| b.is_ascii_lowercase() || b == b'-' || b == b',')
        .then_some(names)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_image_names_its_features_in_its_bytes() {
        let all = Features {
            can: true,
            host_link: true,
            wifi: true,
            store: true,
        };
        let mut image = [0xAAu8; 200];
        image[77..77 + FEATURES_TAG_LEN].copy_from_slice(&all.tag());
        assert_eq!(features_in_image(&image), Some("can,host-link,wifi,store"));
        assert_eq!(all.bits(), 0b1111);
        let wifi_only = Features {
            wifi: true,
            ..Features::default()
        };
        assert_eq!(wifi_only.bits(), 1 << 2);
        assert_eq!(wifi_only.names().as_slice(), ["wifi"]);
        let none = Features::default().tag();
        image[77..77 + FEATURES_TAG_LEN].copy_from_slice(&none);
        assert_eq!(features_in_image(&image), Some(""));
        assert_eq!(features_in_image(&[0u8; 100]), None);
        // The mark without its end (a cut image) names nothing.
        assert_eq!(features_in_image(b"..tinybms-features=can,wi"), None);
    }
}
