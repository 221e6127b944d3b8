//! An example reader of the shared telemetry: it always knows the age of what
//! it reads, and says so when the data goes stale.

use defmt::{info, warn};
use embassy_executor::Spawner;
use embassy_time::{with_timeout, Duration, Instant};

use crate::{spawn, TELEMETRY};

/// Telemetry older than this is reported stale.
const STALE_AFTER: Duration = Duration::from_secs(5);

/// Starts the stale watch.
pub fn start(spawner: Spawner) {
    spawn(spawner, stale_task());
}

/// An example reader of the shared telemetry: it always knows the age of what it
/// reads, and says so when the data goes stale.
#[embassy_executor::task]
async fn stale_task() {
    let Some(mut receiver) = TELEMETRY.receiver() else {
        warn!("telemetry watch has no free receiver slot");
        return;
    };
    let mut stale = false;
    loop {
        match with_timeout(STALE_AFTER, receiver.changed()).await {
            Ok(shared) => {
                if stale {
                    info!("telemetry fresh again");
                    stale = false;
                }
                let age = Instant::now().saturating_duration_since(shared.taken_at);
                if age > STALE_AFTER {
                    warn!("telemetry is {} ms old", age.as_millis());
                }
                let _ = shared.snapshot.soc_percent();
            }
            Err(_) => {
                if !stale {
                    warn!(
                        "no telemetry for {} s: values are stale",
                        STALE_AFTER.as_secs()
                    );
                    stale = true;
                }
            }
        }
    }
}
