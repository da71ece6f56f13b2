//! A thread-safe LRU keyed by content (u128), bounded by bytes. Content keys never go stale:
//! a changed input has a new key, and the old entry simply ages out.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

/// Shards: threads meshing neighbouring tiles hit the cache for the same bricks many times a
/// tile; one lock would serialize them.
const SHARDS: usize = 16;

#[derive(Debug)]
struct Inner<V> {
    entries: HashMap<u128, (Arc<V>, usize, u64)>,
    order: BTreeMap<u64, u128>,
    bytes: usize,
    clock: u64,
}

/// Values by content key, at most `capacity` bytes, least recently used out first (per shard:
/// the key picks one of 16 shards, each holding a 16th of the capacity).
#[derive(Debug)]
pub struct ByteLru<V> {
    shard_capacity: usize,
    shards: Vec<Mutex<Inner<V>>>,
}

impl<V> ByteLru<V> {
    /// An empty cache of at most `capacity` bytes.
    pub fn new(capacity: usize) -> Self {
        ByteLru {
            shard_capacity: capacity / SHARDS,
            shards: (0..SHARDS)
                .map(|_| {
                    Mutex::new(Inner {
                        entries: HashMap::new(),
                        order: BTreeMap::new(),
                        bytes: 0,
                        clock: 0,
                    })
                })
                .collect(),
        }
    }

    fn shard(&self, key: u128) -> &Mutex<Inner<V>> {
        // Keys are hashes already: their low bits are uniform.
        &self.shards[key as usize % SHARDS]
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.shards
            .iter()
            .map(|s| s.lock().map(|l| l.bytes).unwrap_or(0))
            .sum()
    }

    /// The value of `key`, now the most recently used.
    pub fn get(&self, key: u128) -> Option<Arc<V>> {
        let mut inner = self.shard(key).lock().ok()?;
        inner.clock += 1;
        let now = inner.clock;
        let (value, old) = {
            let entry = inner.entries.get_mut(&key)?;
            let old = entry.2;
            entry.2 = now;
            (entry.0.clone(), old)
        };
        inner.order.remove(&old);
        inner.order.insert(now, key);
        Some(value)
    }

    /// Keeps `value` (of `size` bytes) unless it alone exceeds its shard's capacity.
    pub fn put(&self, key: u128, value: Arc<V>, size: usize) {
        if size > self.shard_capacity {
            return;
        }
        let Ok(mut inner) = self.shard(key).lock() else {
            return;
        };
        inner.clock += 1;
        let now = inner.clock;
        if let Some((_, old_size, old_stamp)) = inner.entries.insert(key, (value, size, now)) {
            inner.bytes -= old_size;
            inner.order.remove(&old_stamp);
        }
        inner.order.insert(now, key);
        inner.bytes += size;
        while inner.bytes > self.shard_capacity {
            let Some((_, victim)) = inner.order.pop_first() else {
                break;
            };
            if let Some((_, s, _)) = inner.entries.remove(&victim) {
                inner.bytes -= s;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_least_recently_used_within_its_byte_budget() {
        // Keys that are multiples of the shard count share shard 0, of 1000 bytes.
        let c = ByteLru::new(1000 * SHARDS);
        let k = |i: u128| i * SHARDS as u128;
        for i in 1..=3u128 {
            c.put(k(i), Arc::new(i), 300);
        }
        assert_eq!(c.bytes(), 900);
        assert!(c.get(k(1)).is_some()); // 1 is now the most recent; 2 the least
        c.put(k(4), Arc::new(4), 300);
        assert!(c.get(k(2)).is_none());
        assert!(c.get(k(1)).is_some() && c.get(k(3)).is_some() && c.get(k(4)).is_some());
        assert!(c.bytes() <= 1000);
        c.put(k(5), Arc::new(5), 1001); // larger than the shard's budget: not kept
        assert!(c.get(k(5)).is_none());
        c.put(k(3), Arc::new(33), 100); // replacing an entry frees its old size
        assert_eq!(*c.get(k(3)).unwrap(), 33);
        assert_eq!(c.bytes(), 700);
        // Other shards have their own budget.
        c.put(1, Arc::new(1), 900);
        assert_eq!(c.bytes(), 1600);
    }
}
