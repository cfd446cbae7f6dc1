//! The histogram stage's cache of decoded depth-map pyramids, shared by its workers.

use crate::kernels::votes::Pyramid;
use crate::store::Result;

/// Bytes of decoded pyramids kept between units when the caller sets no budget.
pub const DEFAULT_PYRAMID_CACHE_BYTES: u64 = 128 << 20;

/// Decoded pyramids shared by the workers, least recently used first out, bounded in bytes
/// (or one pyramid, when a single one is larger than the bound).
/// Units run in key order, so neighbouring units (which see mostly the same depth maps) reuse
/// each other's decodes. A pyramid is the same whether cached or decoded again, so the cache
/// changes time, never results.
pub(super) struct PyramidCache {
    pub(super) capacity: u64,
    state: std::sync::Mutex<CacheState>,
    /// Signalled when a decode ends: a worker that wants a map another worker is decoding
    /// waits for that decode instead of making a second copy.
    decoded: std::sync::Condvar,
}

#[derive(Default)]
struct CacheState {
    entries: std::collections::HashMap<u64, (std::sync::Arc<Pyramid>, u64)>,
    /// Maps being decoded now.
    decoding: std::collections::HashSet<u64>,
    bytes: u64,
    clock: u64,
    hits: u64,
    misses: u64,
    /// Pyramids evicted to make room, since the cache was made.
    evictions: u64,
}

impl PyramidCache {
    pub(super) fn new(capacity: u64) -> PyramidCache {
        PyramidCache {
            capacity,
            state: std::sync::Mutex::default(),
            decoded: std::sync::Condvar::new(),
        }
    }

    pub(super) fn get_or_load(
        &self,
        id: u64,
        load: impl FnOnce() -> Result<Pyramid>,
    ) -> Result<std::sync::Arc<Pyramid>> {
        {
            let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
            loop {
                state.clock += 1;
                let now = state.clock;
                if let Some((pyramid, used)) = state.entries.get_mut(&id) {
                    *used = now;
                    let pyramid = pyramid.clone();
                    state.hits += 1;
                    return Ok(pyramid);
                }
                if self.capacity == 0 || !state.decoding.contains(&id) {
                    break;
                }
                state = self
                    .decoded
                    .wait(state)
                    .unwrap_or_else(|poisoned| poisoned.into_inner());
            }
            state.misses += 1;
            state.decoding.insert(id);
        }
        // Decoded outside the lock, so other maps decode meanwhile. The guard ends the decode
        // for the waiters even if `load` unwinds.
        let guard = DecodeGuard { cache: self, id };
        let loaded = load().map(std::sync::Arc::new);
        drop(guard);
        let pyramid = loaded?;
        let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        let size = pyramid.bytes();
        if self.capacity == 0 {
            return Ok(pyramid);
        }
        // A pyramid larger than the whole cache is kept alone until the next insert: its units
        // (a huge map is seen by many in a row) then share one decode, and the workers one
        // copy, where each unit decoded it again (an 8000x6000 map: 54 decodes, two copies).
        let room = self.capacity.max(size);
        while state.bytes + size > room {
            let Some(oldest) = state
                .entries
                .iter()
                .min_by_key(|(_, (_, used))| *used)
                .map(|(id, _)| *id)
            else {
                break;
            };
            if let Some((evicted, _)) = state.entries.remove(&oldest) {
                state.bytes = state.bytes.saturating_sub(evicted.bytes());
                state.evictions += 1;
            }
        }
        let now = state.clock;
        if state.entries.insert(id, (pyramid.clone(), now)).is_none() {
            state.bytes += size;
        }
        Ok(pyramid)
    }

    fn end_decode(&self, id: u64) {
        let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        state.decoding.remove(&id);
        self.decoded.notify_all();
    }

    /// Pyramids evicted so far.
    pub(super) fn evictions(&self) -> u64 {
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .evictions
    }

    /// Drops every cached pyramid (the ones in use stay alive with their users).
    pub(super) fn clear(&self) {
        let mut state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        state.entries.clear();
        state.bytes = 0;
    }

    pub(super) fn counts(&self) -> (u64, u64) {
        let state = self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
        (state.hits, state.misses)
    }
}

/// Ends a decode of the pyramid cache when dropped.
struct DecodeGuard<'c> {
    cache: &'c PyramidCache,
    id: u64,
}

impl Drop for DecodeGuard<'_> {
    fn drop(&mut self) {
        self.cache.end_decode(self.id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inputs::{DepthImage, DepthMapSource};

    fn pyramid() -> Result<Pyramid> {
        let (width, height) = (16, 12);
        let source = DepthMapSource::test_pinhole(
            "map.pfm",
            (width, height),
            [10.0, 10.0, 7.5, 5.5],
            glam::DMat4::IDENTITY,
        );
        let depth = vec![1.0; (width * height) as usize];
        Ok(Pyramid::new(source, DepthImage { width, height, depth }))
    }

    #[test]
    fn evictions_are_counted_and_a_cleared_cache_decodes_again() {
        let size = pyramid().map(|p| p.bytes()).unwrap_or(0);
        // Room for two pyramids.
        let cache = PyramidCache::new(2 * size);
        for id in 0..2 {
            cache.get_or_load(id, pyramid).unwrap();
        }
        assert_eq!((cache.evictions(), cache.counts()), (0, (0, 2)));
        cache.get_or_load(0, pyramid).unwrap();
        cache.get_or_load(2, pyramid).unwrap();
        // Map 1 was the least recently used.
        assert_eq!((cache.evictions(), cache.counts()), (1, (1, 3)));
        cache.get_or_load(0, pyramid).unwrap();
        assert_eq!(cache.counts(), (2, 3));
        cache.clear();
        cache.get_or_load(0, pyramid).unwrap();
        assert_eq!((cache.evictions(), cache.counts()), (1, (2, 4)));
    }
}
