//! The MQTT end-to-end scenario over the chip's network stack: the firmware's
//! session on embassy-net (`tinybms_firmware::mqtt::net`, the chip's code) on a
//! TAP device, talking to Debian's `mosquitto` on the kernel's side of it —
//! private addresses in a network namespace of its own.
//!
//! Run as `unshare -n -- mqtt-tap` (root, or a user namespace: `unshare -rn`):
//! it refuses to touch a namespace that has any interface besides `lo`, so it
//! never changes the machine's network. Exit status 0 when every check passed.
//!
//! Kernel side `tap0` 10.42.0.1/24 (the broker); embassy-net 10.42.0.2/24
//! (static: no DHCP server here; the chip asks DHCP).

#[cfg(target_os = "linux")]
fn main() -> std::process::ExitCode {
    match linux::run() {
        Ok(summary) => {
            println!("mqtt-tap: passed: {summary}");
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("mqtt-tap: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn main() -> std::process::ExitCode {
    eprintln!("mqtt-tap: needs Linux (network namespaces and /dev/net/tun)");
    std::process::ExitCode::FAILURE
}

#[cfg(target_os = "linux")]
mod linux {
    use std::process::Command;

    use embassy_net::tcp::client::{TcpClient, TcpClientState};
    use embassy_net::{Config, Ipv4Address, Ipv4Cidr, StackResources, StaticConfigV4};
    use embassy_net_tuntap::TunTapDevice;
    use host_tests::mqtt::{self as hm, Beside, HostClock, Kill, Killable};
    use host_tests::mqtt_e2e;
    use tinybms_firmware::mqtt::net::StackNet;
    use tinybms_firmware::mqtt::session::Target;
    use tinybms_firmware::mqtt::Settings;

    const BROKER: &str = "10.42.0.1";
    const PORT: u16 = 1883;
    /// The chip's TCP buffers (src/chip/network.rs).
    const TCP_BUFFER: usize = 2048;

    fn ip(args: &[&str]) -> Result<(), String> {
        let out = Command::new("ip")
            .args(args)
            .output()
            .map_err(|e| format!("ip (apt-get install iproute2): {e}"))?;
        if out.status.success() {
            Ok(())
        } else {
            Err(format!(
                "ip {}: {}",
                args.join(" "),
                String::from_utf8_lossy(&out.stderr).trim()
            ))
        }
    }

    /// Only in a namespace of our own: nothing but `lo` may be there. (Asked
    /// of `ip`, not /sys/class/net: sysfs shows the namespace it was mounted in.)
    fn check_namespace() -> Result<(), String> {
        let out = Command::new("ip")
            .args(["-o", "link", "show"])
            .output()
            .map_err(|e| format!("ip (apt-get install iproute2): {e}"))?;
        let text = String::from_utf8_lossy(&out.stdout);
        let names: Vec<&str> = text
            .lines()
            .filter_map(|l| l.split(':').nth(1))
            .map(|n| n.trim().split('@').next().unwrap_or(""))
            .collect();
        if !out.status.success() || names.iter().any(|n| *n != "lo") {
            return Err(format!(
                "interfaces {names:?}: run me in a new network namespace (unshare -n -- mqtt-tap)"
            ));
        }
        Ok(())
    }

    pub fn run() -> Result<String, String> {
        check_namespace()?;
        ip(&["link", "set", "lo", "up"])?;
        ip(&["tuntap", "add", "dev", "tap0", "mode", "tap"])?;
        ip(&["addr", "add", &format!("{BROKER}/24"), "dev", "tap0"])?;
        ip(&["link", "set", "tap0", "up"])?;
        mqtt_e2e::scenario(BROKER, PORT, |b| {
            let kill = Kill::default();
            let k = kill.clone();
            let clock = b.clock;
            let mut target = Target::from_config(&mqtt_e2e::config(), "tinybms-tap");
            let _ = target.host.push_str(BROKER);
            target.port = PORT;
            let device = TunTapDevice::new("tap0").map_err(|e| format!("tap0: {e}"))?;
            let notes = hm::spawn_with(
                target,
                (
                    Settings::from_config(&mqtt_e2e::config()),
                    tinybms_firmware::identity::Identity::desktop("tap", Default::default()),
                ),
                b.shared.clone(),
                clock,
                true,
                move || {
                    let config = Config::ipv4_static(StaticConfigV4 {
                        address: Ipv4Cidr::new(Ipv4Address::new(10, 42, 0, 2), 24),
                        gateway: None,
                        dns_servers: Default::default(),
                    });
                    // 'static as on the chip (StaticCell there): this thread
                    // runs until the process ends.
                    let resources = Box::leak(Box::new(StackResources::<3>::new()));
                    let (stack, mut runner) = embassy_net::new(device, config, resources, 7);
                    let state =
                        Box::leak(Box::new(TcpClientState::<1, TCP_BUFFER, TCP_BUFFER>::new()));
                    let mut client = TcpClient::new(stack, state);
                    client.set_timeout(Some(embassy_time::Duration::from_secs(30)));
                    let net = StackNet::new(stack, client, HostClock(clock), |a| {
                        eprintln!("mqtt-tap: embassy-net address {a}")
                    });
                    let beside: Beside = Box::pin(async move { runner.run().await });
                    (Killable { net, kill: k }, beside)
                },
            );
            Ok((kill, notes))
        })
    }
}
