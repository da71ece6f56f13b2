//! Taking turns at the head: how a replica whose edits keep losing the head race asks the
//! others to leave it a gap.
//!
//! A replica that keeps its queue full wins every race against one that lost: having made the
//! head itself, its catch-up is a 304 and it stages its next group at once, while the loser
//! must fetch the new head and its commit records first and arrives a round late, every round
//! (measured: of two replicas under 8 editors each, one acknowledged under 1 edit/s, and its
//! editors were answered 503). So a replica that lost twice in a row writes the small object
//! `turn`: its id and how long its lost attempt took, from catching up to the refused PUT. A
//! replica that commits looks at `turn` now and then (a conditional GET, 304 while nothing
//! changed), and while another replica asked within the last [`WAITING_FOR`], it pauses after
//! each won group for as long as the loser said it needs. The two then take turns; the edits
//! that arrive during a pause join the pausing replica's next group.

use super::bucket::{Bucket, Conditional};
use bytes::Bytes;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The object a losing replica writes.
pub const TURN_KEY: &str = "turn";

/// A replica asks at most this often, and looks at most this often.
const EVERY: Duration = Duration::from_millis(20);

/// How long after the last ask the others keep pausing.
const WAITING_FOR: Duration = Duration::from_millis(300);

/// One replica's side of the turns of one volume.
#[derive(Debug)]
pub struct Turns {
    /// This replica's id, what it writes.
    id: [u8; 8],
    state: Mutex<Seen>,
}

#[derive(Debug, Default)]
struct Seen {
    /// The ETag of `turn` when last read.
    etag: Option<String>,
    /// When `turn` was last looked at.
    looked: Option<Instant>,
    /// When another replica's ask was last seen, and the time its attempts take.
    asked_by_another: Option<(Instant, Duration)>,
    /// When this replica last asked.
    asked: Option<Instant>,
}

fn recently(at: Option<Instant>, within: Duration) -> bool {
    at.is_some_and(|t| t.elapsed() < within)
}

/// The time another replica's attempts take, if it asked lately.
fn waiting(seen: &Seen) -> Option<Duration> {
    seen.asked_by_another
        .filter(|(at, _)| at.elapsed() < WAITING_FOR)
        .map(|(_, needs)| needs)
}

impl Default for Turns {
    fn default() -> Self {
        Turns {
            id: rand::random::<u64>().to_le_bytes(),
            state: Mutex::default(),
        }
    }
}

impl Turns {
    fn seen(&self) -> std::sync::MutexGuard<'_, Seen> {
        // Every update is a plain assignment: a poisoned lock holds a sound state.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Asks the other replicas for a gap (this replica lost the head race again; its attempt
    /// took `needs`). A failure is only logged: the ask is a courtesy, never needed for
    /// correctness.
    pub fn ask(&self, bucket: &Bucket, needs: Duration) {
        {
            let mut seen = self.seen();
            if recently(seen.asked, EVERY) {
                return;
            }
            seen.asked = Some(Instant::now());
        }
        let micros = u32::try_from(needs.as_micros()).unwrap_or(u32::MAX);
        let body: Vec<u8> = self
            .id
            .iter()
            .copied()
            .chain(micros.to_le_bytes())
            .collect();
        if let Err(e) = bucket.put(TURN_KEY, Bytes::from(body)) {
            tracing::debug!(error = %crate::store::error_chain(&e), "cannot ask for a turn at the head");
        }
    }

    /// How long another replica that asked for a gap within the last [`WAITING_FOR`] needs
    /// for an attempt; `None` when none asked.
    pub fn others_wait(&self, bucket: &Bucket) -> Option<Duration> {
        let etag = {
            let mut seen = self.seen();
            if recently(seen.looked, EVERY) {
                return waiting(&seen);
            }
            seen.looked = Some(Instant::now());
            seen.etag.clone()
        };
        match bucket.get_if_changed(TURN_KEY, etag.as_deref()) {
            Ok(Conditional::Done(Some(body), etag)) => {
                let mut seen = self.seen();
                // The first look only learns the ETag: an ask older than this replica says
                // nothing about now.
                let (id, needs) = body.split_at(body.len().min(8));
                if seen.etag.is_some() && id != self.id {
                    let micros = needs
                        .get(..4)
                        .map_or(0, |m| u32::from_le_bytes([m[0], m[1], m[2], m[3]]));
                    let needs = Duration::from_micros(u64::from(micros));
                    seen.asked_by_another = Some((Instant::now(), needs));
                }
                seen.etag = Some(etag);
            }
            Ok(_) => {}
            Err(e) => {
                tracing::debug!(error = %crate::store::error_chain(&e), "cannot look at the turns at the head");
            }
        }
        waiting(&self.seen())
    }
}
