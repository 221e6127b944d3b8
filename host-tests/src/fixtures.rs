//! What the tests build again and again, built once: a station at time 0, a
//! pack's summary as the packs of a battery exchange it, a member of that
//! battery, and the view of a battery of packs the host link and MQTT
//! publish. A test changes
//! what it is about with struct update syntax (`Summary { age_ds: 2,
//! ..pack_summary() }`) and leaves the rest to these.

use tinybms_firmware::bms::timing::Timing;
use tinybms_firmware::config::store::{Loaded, Source};
use tinybms_firmware::config::Config;
use tinybms_firmware::freshness::Freshness;
use tinybms_firmware::identity::Identity;
use tinybms_firmware::inverter::control::{Conditions, Limits};
use tinybms_firmware::inverter::packs::{
    aggregate, BatteryView, Member, PackPart, PackView, Summary,
};
use tinybms_firmware::station::{Setup, Station};
use tinybms_firmware::SECOND;

/// The station of a bridge that is `identity`, at time 0, with the default
/// timing, started from an empty store with `config` as its record.
pub fn station(identity: Identity, config: Config) -> Station {
    let setup = Setup {
        timing: Timing::default(),
        identity,
        inverter: None,
    };
    let loaded = Loaded {
        config,
        source: Source::Empty,
    };
    Station::new(setup, loaded, 0)
}

/// A 16-cell LiFePO4 pack of 280 Ah at 53.21 V, discharging 4.1 A, 65.43 %
/// charged, its cells 3.301-3.345 V and its sensors 21.5-24.8 °C, heard
/// 0.7 s ago; CVL 55.2 V, CCL 58.8 A, DCL 117.6 A, discharge to 48.0 V; no
/// condition, no fault, not the speaker.
pub fn pack_summary() -> Summary {
    Summary {
        voltage_cv: 5321,
        current_da: -41,
        soc_cpct: 6543,
        soh_pct: 97,
        min_cell_mv: 3301,
        max_cell_mv: 3345,
        min_temp_dc: 215,
        max_temp_dc: 248,
        age_ds: 7,
        capacity_dah: 2800,
        limits: Limits {
            cvl_dv: 552,
            ccl_da: 588,
            dcl_da: 1176,
            discharge_dv: 480,
        },
        conditions: Conditions::default(),
        fault: false,
        charge_blocked: false,
        speaking: false,
    }
}

/// `summary` as a member of the battery, heard just now (`alive`: within the
/// time a pack is kept), with no limits kept from before a fault.
pub fn member(summary: Summary, alive: bool) -> Member {
    Member {
        summary,
        alive,
        heard_ago_us: 0,
        closed_limits: None,
    }
}

/// What bridge 1 sees of a battery whose packs are `packs` (node, summary,
/// part, from node 1): the battery aggregated from those taking part (with
/// a stale limit of 5 s) and sent with `sent` as its limits (`None`: as
/// aggregated), or no battery when `with_battery` is false.
pub fn battery_view(
    speaking: bool,
    packs: &[(u8, Summary, PackPart)],
    with_battery: bool,
    sent: impl FnOnce(Limits) -> Limits,
) -> BatteryView {
    let members: Vec<Member> = packs
        .iter()
        .map(|&(_, s, part)| member(s, part != PackPart::Lost))
        .collect();
    let battery = aggregate(&members, Freshness::new(5 * SECOND)).expect("a pack takes part");
    let mut views = heapless::Vec::new();
    for &(node, summary, part) in packs {
        let _ = views.push(PackView {
            node,
            summary,
            part,
        });
    }
    BatteryView {
        node: 1,
        speaking,
        battery: with_battery.then(|| (battery, sent(battery.limits))),
        packs: views,
    }
}

/// A live snapshot of 16 cells with every value at its widest (the longest
/// `telemetry` line and MQTT state are measured with it).
pub fn widest_snapshot() -> protocol_core::views::LiveSnapshot {
    let mut block = protocol_core::response::RegisterBlock {
        start: 0,
        values: Default::default(),
    };
    for a in 0..56u16 {
        let v = match a {
            0..=15 => 49_999,
            36..=39 => 0xBF7F, // f32 halves
            53 => 16,
            48 | 42 | 43 => 0x8001,
            _ => 0xFFFF,
        };
        block.values.push(v).expect("56 registers fit");
    }
    protocol_core::views::LiveSnapshot::from_registers(&block).expect("a snapshot")
}
