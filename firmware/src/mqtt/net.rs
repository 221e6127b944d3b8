//! The session's network on embassy-net (feature `net`): one implementation
//! for the chip (over the Wi-Fi station) and for the host's namespace test
//! (over a TAP device), so the test drives the code the chip runs.
//!
//! Each connection is one TCP socket from a one-slot [`TcpClient`] pool; the
//! caller builds the client (its buffers and its timeout). A connect waits at
//! most [`WAIT_FOR_ADDRESS_US`] for an address, then reports
//! [`NetError::NoNetwork`] so the session backs off instead of waiting forever.

use core::net::{IpAddr, SocketAddr};

use embassy_futures::select::select;
use embassy_net::dns::DnsQueryType;
use embassy_net::tcp::client::{TcpClient, TcpConnection};
use embassy_net::{Ipv4Cidr, Stack};
use embedded_nal_async::TcpConnect;

use super::session::{Clock, NetError, Network};

/// How long a connect waits for the stack to have an address, µs.
pub const WAIT_FOR_ADDRESS_US: u64 = 5_000_000;

/// TCP to the broker through an embassy-net stack.
pub struct StackNet<'d, C: Clock, const TX: usize, const RX: usize> {
    stack: Stack<'d>,
    client: TcpClient<'d, 1, TX, RX>,
    clock: C,
    on_address: fn(Ipv4Cidr),
    address_noted: bool,
}

impl<'d, C: Clock, const TX: usize, const RX: usize> StackNet<'d, C, TX, RX> {
    /// Connections of `client` on `stack`; `on_address` is called once per
    /// address the stack gets (for the log).
    pub fn new(
        stack: Stack<'d>,
        client: TcpClient<'d, 1, TX, RX>,
        clock: C,
        on_address: fn(Ipv4Cidr),
    ) -> Self {
        Self {
            stack,
            client,
            clock,
            on_address,
            address_noted: false,
        }
    }
}

impl<'d, C: Clock, const TX: usize, const RX: usize> Network for StackNet<'d, C, TX, RX> {
    type Conn<'a>
        = TcpConnection<'a, 1, TX, RX>
    where
        Self: 'a;

    async fn connect<'a>(&'a mut self, host: &str, port: u16) -> Result<Self::Conn<'a>, NetError> {
        if !self.stack.is_config_up() {
            self.address_noted = false;
            // The session is the only task that waits on the stack's state
            // (embassy-net keeps one waker for it).
            let until = self.clock.now().saturating_add(WAIT_FOR_ADDRESS_US);
            let _ = select(self.stack.wait_config_up(), self.clock.sleep_until(until)).await;
            if !self.stack.is_config_up() {
                return Err(NetError::NoNetwork);
            }
        }
        if !self.address_noted {
            self.address_noted = true;
            if let Some(c) = self.stack.config_v4() {
                (self.on_address)(c.address);
            }
        }
        // An address literal is taken as it is; a name asks the stack's DNS.
        let addrs = self
            .stack
            .dns_query(host, DnsQueryType::A)
            .await
            .map_err(|_| NetError::Dns)?;
        let ip: IpAddr = addrs.first().copied().ok_or(NetError::Dns)?.into();
        self.client
            .connect(SocketAddr::new(ip, port))
            .await
            .map_err(|_| NetError::Connect)
    }
}
