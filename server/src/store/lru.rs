//! A thread-safe LRU keyed by content (u128), bounded by bytes. Content keys never go stale:
//! a changed input has a new key, and the old entry simply ages out.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

#[derive(Debug)]
struct Inner<V> {
    entries: HashMap<u128, (Arc<V>, usize, u64)>,
    order: BTreeMap<u64, u128>,
    bytes: usize,
    clock: u64,
}

/// Values by content key, at most `capacity` bytes, least recently used out first.
#[derive(Debug)]
pub struct ByteLru<V> {
    capacity: usize,
    inner: Mutex<Inner<V>>,
}

impl<V> ByteLru<V> {
    pub fn new(capacity: usize) -> Self {
        ByteLru {
            capacity,
            inner: Mutex::new(Inner {
                entries: HashMap::new(),
                order: BTreeMap::new(),
                bytes: 0,
                clock: 0,
            }),
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.inner.lock().map(|l| l.bytes).unwrap_or(0)
    }

    pub fn get(&self, key: u128) -> Option<Arc<V>> {
        let mut inner = self.inner.lock().ok()?;
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

    /// Keeps `value` (of `size` bytes) unless it alone exceeds the capacity.
    pub fn put(&self, key: u128, value: Arc<V>, size: usize) {
        if size > self.capacity {
            return;
        }
        let Ok(mut inner) = self.inner.lock() else {
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
        while inner.bytes > self.capacity {
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
        let c = ByteLru::new(1000);
        for k in 1..=3u128 {
            c.put(k, Arc::new(k), 300);
        }
        assert_eq!(c.bytes(), 900);
        assert!(c.get(1).is_some()); // 1 is now the most recent; 2 the least
        c.put(4, Arc::new(4), 300);
        assert!(c.get(2).is_none());
        assert!(c.get(1).is_some() && c.get(3).is_some() && c.get(4).is_some());
        assert!(c.bytes() <= 1000);
        c.put(5, Arc::new(5), 1001); // larger than the whole budget: not kept
        assert!(c.get(5).is_none());
        c.put(3, Arc::new(33), 100); // replacing an entry frees its old size
        assert_eq!(*c.get(3).unwrap(), 33);
        assert_eq!(c.bytes(), 700);
    }
}
