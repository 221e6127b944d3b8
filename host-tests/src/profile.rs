//! Settings profiles: `name = value` lines (the format, its reader and its
//! messages are [`tinybms_rules::profile`], shared with the browser console).

pub use tinybms_rules::profile::*;
