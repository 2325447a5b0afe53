//! The position grid every curve is kept on: [`BINS`] bins over the compliant stroke,
//! by insertion depth (µm past the engagement point), the same for both strokes.
//!
//! A curve on a position grid, not in time, compares strokes at any speed (a slower
//! axis fills its bins with more samples, not a longer curve). Bin `i` covers depths
//! `[lo(i), lo(i + 1))` with `lo(i) = ⌊i · STROKE_UM / BINS⌋` µm: 234 or 235 µm each
//! over the 30 mm stroke. A sample past the end of the stroke (the mated position,
//! where the insertion stops, lies exactly at 30 mm) up to [`END_MARGIN_UM`] beyond it
//! goes into the last bin; one before the cone's mouth, or further past the end, into
//! none.
//!
//! ```text
//!  depth 0                                                          STROKE_UM (30 mm)
//!  |  bin 0 |  bin 1 |  bin 2 |   ...                     | bin 126 | bin 127 |+margin
//!  0       234      468      703                        29531     29765    30000
//! ```

use crate::profile::STROKE_UM;

/// Bins over the stroke.
pub const BINS: usize = 128;

/// How far past the end of the stroke a sample still counts (into the last bin), µm.
pub const END_MARGIN_UM: i32 = 500;

/// [`BINS`] as an `i32`.
const BINS_I32: i32 = BINS as i32;

/// The bin a sample at `depth_um` falls into, or `None` outside the stroke.
pub const fn bin_of(depth_um: i32) -> Option<usize> {
    if depth_um < 0 || depth_um > STROKE_UM + END_MARGIN_UM {
        None
    } else if depth_um >= STROKE_UM {
        Some(BINS - 1)
    } else {
        // The last bin whose first depth (⌊i·STROKE/BINS⌋) is at or before the depth;
        // depth < 30 000: the product fits i32 (3.84e6).
        Some((((depth_um + 1) * BINS_I32 - 1) / STROKE_UM) as usize)
    }
}

/// The first depth of bin `i`, µm (`lo(BINS)` is the end of the stroke).
pub const fn lo_um(i: usize) -> i32 {
    let i = if i > BINS { BINS } else { i };
    (i as i32) * STROKE_UM / BINS_I32
}

/// The middle of bin `i`, µm.
pub const fn mid_um(i: usize) -> i32 {
    (lo_um(i) + lo_um(i + 1)) / 2
}

/// Bin `i`'s width, µm.
pub const fn width_um(i: usize) -> i32 {
    lo_um(i + 1) - lo_um(i)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_depth_of_the_stroke_has_its_bin_and_the_bins_tile_it() {
        assert_eq!(lo_um(0), 0);
        assert_eq!(lo_um(BINS), STROKE_UM);
        for d in 0..STROKE_UM {
            let i = bin_of(d).unwrap();
            assert!(lo_um(i) <= d && d < lo_um(i + 1), "{d} in bin {i}");
        }
        assert_eq!(bin_of(-1), None);
        assert_eq!(bin_of(STROKE_UM), Some(BINS - 1));
        assert_eq!(bin_of(STROKE_UM + END_MARGIN_UM), Some(BINS - 1));
        assert_eq!(bin_of(STROKE_UM + END_MARGIN_UM + 1), None);
        assert!((0..BINS).all(|i| (234..=235).contains(&width_um(i))));
    }
}
