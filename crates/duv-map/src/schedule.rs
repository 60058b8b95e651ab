//! Which keyframe the next mapping iteration optimises (paper §3.3): mostly one of the newest
//! window, sometimes a random older one, so early parts of the map are not forgotten.

use duv_core::rng::Rng;

/// Picks a keyframe slot among `count` (oldest first): with probability `window_probability`
/// uniformly among the newest `window`, otherwise uniformly among the older ones (the window
/// when there are none). `count` must be > 0.
pub fn pick_keyframe(rng: &mut Rng, count: usize, window: usize, window_probability: f64) -> usize {
    debug_assert!(count > 0);
    let window = window.clamp(1, count);
    let older = count - window;
    if older == 0 || rng.uniform() < window_probability {
        older + rng.below(window as u64) as usize
    } else {
        rng.below(older as u64) as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn picks_window_mostly_and_older_sometimes() {
        let mut rng = Rng::new(3);
        let mut hits = [0usize; 10];
        for _ in 0..10_000 {
            hits[pick_keyframe(&mut rng, 10, 3, 0.75)] += 1;
        }
        let window: usize = hits[7..].iter().sum();
        assert!((7200..7800).contains(&window), "{hits:?}");
        assert!(hits[..7].iter().all(|&h| h > 200), "every older keyframe is revisited: {hits:?}");
        assert_eq!(pick_keyframe(&mut rng, 1, 3, 0.0), 0);
    }
}
