//! Group commit on an object store: the edits waiting for a replica's writer become one segment
//! and one conditional PUT of the head (the segment carried in it when small), as a group on a
//! local file becomes one sync (`group.rs`).
//!
//! A commit on an object store costs one or two requests in series whatever it holds, and the
//! head's PUT admits one commit at a time for the whole volume: committed one by one, the edits of all
//! replicas together were bounded by that one PUT's rate. So a replica's writer takes its queue
//! as a group, as on a file:
//!
//! 1. catch up with the head (one conditional GET);
//! 2. stage each edit in turn on the version before it (`If-Match` checked against that
//!    version): its bricks and commit record go to the writer's buffer, and the buffer is
//!    written into the mirror file past the head's segments, so the next edit reads the
//!    version it builds on as any version is read (`RemoteVolume::staged`). A failing edit is
//!    rolled back alone;
//! 3. publish: one segment with every version's bytes, carried in the head or written first,
//!    then the head naming the last version, conditional on the head the group was staged on;
//! 4. serve, announce and answer each version in order.
//!
//! When another writer won the head meanwhile (3 refused), the whole group is staged again on
//! top of the new head, with a random wait that doubles with each loss, up to
//! [`MAX_REMOTE_ATTEMPTS`] times; an edit with `If-Match` is then refused, since its version is
//! gone. An edit is acknowledged only after the head's PUT succeeded: a replica killed during a
//! group loses nothing it acknowledged, and an object it may have left is garbage for
//! `compact`.

use super::group::{copy_of, micros, EditAnswer, PendingEdit, Work};
use super::{change_event, LiveVolume, VolumeError, WriterSlot};
use crate::cancel::CancelToken;
use crate::store::remote::backoff::Backoff;
use crate::store::remote::{bound_store_waits, RemoteVolume};
use crate::store::{CheckpointPolicy, StoreError, Vod2, Vod2Writer};
use isovox_proto::api::ChangeEvent;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Times a group is staged against other writers of an object-store volume before its edits
/// are answered that the volume is too busy (503, retry).
const MAX_REMOTE_ATTEMPTS: u32 = 16;

/// The wait after a first lost head race is drawn from [1, 2] ms; each further loss doubles the
/// range, up to [50, 100] ms (at most about 1 s over all the attempts). A race is lost to a
/// commit that just landed, so the next try soon after usually wins.
const LOST_RACE_FIRST_WAIT: Duration = Duration::from_millis(2);
/// See [`LOST_RACE_FIRST_WAIT`].
const LOST_RACE_MAX_WAIT: Duration = Duration::from_millis(100);

/// The shortest and longest pause a replica leaves another that asked for a turn (see
/// [`LiveVolume::leave_the_head_a_turn`]).
const MIN_TURN: Duration = Duration::from_millis(5);
/// See [`MIN_TURN`].
const MAX_TURN: Duration = Duration::from_millis(100);

/// An edit of the group with what its evaluation is stopped by and when it started.
struct Member {
    pending: PendingEdit,
    cancel: CancelToken,
    started: Instant,
}

/// What one attempt made of an edit: a staged version (served once the group is published)
/// and its answer, or only an answer (a conflict, a failure, a dry run).
struct Outcome {
    version: Option<(Arc<Vod2>, ChangeEvent)>,
    answer: EditAnswer,
}

impl LiveVolume {
    /// Commits `group` to this object-store volume (see the module's documentation), holding
    /// the writer, and answers every edit. Blocking.
    pub(super) fn commit_group_remote(
        &self,
        remote: &Arc<RemoteVolume>,
        slot: &mut WriterSlot,
        group: Vec<PendingEdit>,
        policy: CheckpointPolicy,
    ) {
        let mut members: Vec<Member> = group
            .into_iter()
            .filter(|p| !p.withdrawn())
            .map(|pending| Member {
                cancel: pending.cancel.restarted(),
                started: Instant::now(),
                pending,
            })
            .collect();
        if members.is_empty() {
            return;
        }
        // Store calls give up when no edit of the group can still be answered in time (503,
        // the store's fault) rather than wait out a stalled store; the head's PUT alone waits
        // on (see its comment). An edit without a deadline waits as long as the store takes.
        let deadlines: Option<Vec<(Instant, Duration)>> =
            members.iter().map(|m| m.cancel.deadline()).collect();
        let deadline = deadlines.and_then(|d| d.into_iter().max_by_key(|(at, _)| *at));
        let mut lost_races = Backoff::new(LOST_RACE_FIRST_WAIT, LOST_RACE_MAX_WAIT);
        let mut attempt = 0u32;
        let mut won = false;
        let outcomes = loop {
            let bounded = bound_store_waits(deadline);
            let began = Instant::now();
            match self.stage_and_publish(remote, slot, &mut members, policy) {
                Ok(outcomes) => {
                    drop(bounded);
                    won = true;
                    break Ok(outcomes);
                }
                Err(StoreError::HeadMoved { .. }) if attempt + 1 < MAX_REMOTE_ATTEMPTS => {
                    drop(bounded);
                    attempt += 1;
                    if attempt >= 2 {
                        remote.ask_for_a_turn(began.elapsed());
                    }
                    // Writers that collide again and again back off apart: exponentially,
                    // with jitter, so the losers do not all come back at the same instant.
                    std::thread::sleep(lost_races.next_wait());
                }
                Err(e) => break Err(e),
            }
        };
        match outcomes {
            Ok(outcomes) => {
                for (m, o) in members.into_iter().zip(outcomes) {
                    if let Some((vod, event)) = o.version {
                        self.publish(vod, event);
                    }
                    let answer = o.answer.map(|mut r| {
                        r.elapsed_us = micros(m.started.elapsed());
                        r
                    });
                    m.pending.answer(answer);
                }
            }
            Err(e) => {
                tracing::warn!(volume = %self.name, error = %crate::store::error_chain(&e), edits = members.len(), "an edit group was not committed");
                for m in members {
                    m.pending.answer(Err(copy_of(&e).into()));
                }
            }
        }
        self.leave_the_head_a_turn(remote, won);
    }

    /// After a won head race, while another replica asks for a turn: pauses for as long as
    /// the other's attempts take (catching up, staging and publishing its group), between
    /// [`MIN_TURN`] and [`MAX_TURN`] (`store/remote/turns.rs` says why). The group is
    /// answered already; edits that arrive meanwhile wait for the next. (Pausing only while
    /// edits waited here was not enough: with two editors a replica, the queue was empty at
    /// that instant and filled again a moment later. Pausing for a multiple of this replica's
    /// own attempt was not either: a winner's attempt is the shorter one. Half the other's
    /// attempt starved it again, 503s included; twice it left the winner idle after the other
    /// had committed: 3-15% fewer edits/s in 8 alternating pairs of runs with 8 editors on
    /// each of two replicas.)
    fn leave_the_head_a_turn(&self, remote: &RemoteVolume, won: bool) {
        if !won {
            return;
        }
        if let Some(needs) = remote.others_wait() {
            std::thread::sleep(needs.clamp(MIN_TURN, MAX_TURN));
        }
    }

    /// One attempt: catch up with the head, stage every member on the version before it,
    /// publish them in one segment and one head PUT (the segment in it when small). Returns
    /// each member's outcome, in order; nothing is served yet.
    ///
    /// # Errors
    /// [`StoreError::HeadMoved`]: another writer's commit came first (stage again); the store
    /// or the mirror failed (the whole group fails).
    fn stage_and_publish(
        &self,
        remote: &Arc<RemoteVolume>,
        slot: &mut WriterSlot,
        members: &mut [Member],
        policy: CheckpointPolicy,
    ) -> Result<Vec<Outcome>, StoreError> {
        self.catch_up(slot)?;
        let base = self.current();
        let mut writer = Vod2Writer::remote(&base, remote.clone());
        let mut tip = base;
        let mut outcomes = Vec::with_capacity(members.len());
        for m in members.iter_mut() {
            let head = tip.head_ref();
            let previous = head.version;
            if let Some(expected) = m.pending.if_match.filter(|&v| v != previous) {
                outcomes.push(Outcome {
                    version: None,
                    answer: Err(VolumeError::Conflict {
                        expected,
                        current: previous,
                    }),
                });
                continue;
            }
            let dry_run = matches!(m.pending.work, Work::Edit { dry_run: true, .. });
            let savepoint = writer.savepoint();
            match self.stage_only(&mut writer, head, &mut m.pending.work, policy, &m.cancel) {
                Ok(staged) if dry_run => {
                    writer.rollback(savepoint)?;
                    outcomes.push(Outcome {
                        version: None,
                        answer: Ok(staged.dry_run(previous + 1, previous)),
                    });
                }
                Ok(staged) => {
                    let slot = writer.tip().ok_or_else(|| {
                        StoreError::Internal("staging left the writer without a version".into())
                    })?;
                    let (from, bytes) = writer.unpublished().ok_or_else(|| {
                        StoreError::Internal("a remote writer without unpublished bytes".into())
                    })?;
                    let next = Arc::new(remote.staged(&tip, from, bytes, slot)?);
                    let event = change_event(&next, slot.commit)?;
                    let response = staged.response(&event, previous);
                    tip = next.clone();
                    outcomes.push(Outcome {
                        version: Some((next, event)),
                        answer: Ok(response),
                    });
                }
                Err(e) => {
                    writer.rollback(savepoint)?;
                    outcomes.push(Outcome {
                        version: None,
                        answer: Err(e),
                    });
                }
            }
        }
        if writer.has_staged() {
            writer.sync()?;
        }
        Ok(outcomes)
    }
}
