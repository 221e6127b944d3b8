//! Small word helpers the desktop side shares (the profile reader and the
//! tool), from the rules the browser console shares too.

pub use tinybms_rules::words::{short, suggest};
