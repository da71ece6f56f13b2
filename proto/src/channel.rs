//! Attribute channels: categorical values per voxel (a material, a segment label) stored beside
//! a volume's density, one brick stream each, committed in the same versions (`docs/channels.md`).
//!
//! Density is channel 0 and has no entry here; the attribute channels follow in the order the
//! file header lists them. Their values are identifiers, not amounts: coarser levels take the
//! most frequent value of each 2x2x2 group ([`mode_of_8`]), never a mean.

use crate::error::FormatError;
use crate::voxel::VoxelType;
use serde::{Deserialize, Serialize};

/// At most this many attribute channels beside density.
pub const MAX_CHANNELS: usize = 7;
/// At most this many palette entries per channel.
pub const MAX_PALETTE: usize = 256;
/// Longest channel name.
pub const MAX_NAME_LEN: usize = 32;

/// One attribute channel, as the file header's channel table and the volume metadata list it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChannelInfo {
    /// Its name (`material`, `label`, ...): lower-case ASCII letters, digits and `_`, starting
    /// with a letter; never `density`.
    pub name: String,
    /// The type of its values.
    #[serde(rename = "type")]
    pub voxel_type: VoxelType,
    /// Display colours by value (`#rrggbb`), index = value; values past its end have none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub palette: Vec<String>,
    /// Whether 0 (unlabelled) loses to any other value when coarser levels take the most
    /// frequent value of 8 (as segmentations want: a thin labelled structure survives
    /// downsampling), unless all 8 are 0.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub sparse: bool,
}

impl ChannelInfo {
    /// A channel of `voxel_type` named `name`, no palette, 0 counted like any value.
    pub fn new(name: &str, voxel_type: VoxelType) -> ChannelInfo {
        ChannelInfo {
            name: name.to_string(),
            voxel_type,
            palette: Vec::new(),
            sparse: false,
        }
    }

    /// # Errors
    /// A bad name or palette entry (see the fields).
    pub fn validate(&self) -> Result<(), FormatError> {
        let bad = |detail: String| FormatError::invalid("channel", detail);
        let n = &self.name;
        let well_formed = !n.is_empty()
            && n.len() <= MAX_NAME_LEN
            && n.as_bytes()[0].is_ascii_lowercase()
            && n.bytes()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'_');
        if !well_formed || n == "density" {
            return Err(bad(format!(
                "name {n:?}: 1 to {MAX_NAME_LEN} of a-z, 0-9 and _, starting with a letter, and not \"density\""
            )));
        }
        if self.palette.len() > MAX_PALETTE {
            return Err(bad(format!(
                "{n}: {} palette entries, at most {MAX_PALETTE}",
                self.palette.len()
            )));
        }
        if let Some(c) = self.palette.iter().find(|c| parse_colour(c).is_none()) {
            return Err(bad(format!("{n}: palette colour {c:?} is not #rrggbb")));
        }
        Ok(())
    }
}

/// `#rrggbb` as its three bytes.
pub fn parse_colour(c: &str) -> Option<[u8; 3]> {
    let hex = c.strip_prefix('#')?;
    if hex.len() != 6 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    let byte = |i: usize| u8::from_str_radix(&hex[i..i + 2], 16).ok();
    Some([byte(0)?, byte(2)?, byte(4)?])
}

/// Checks a channel list: each channel valid, names distinct, at most [`MAX_CHANNELS`].
///
/// # Errors
/// What is wrong, naming the channel.
pub fn validate_channels(channels: &[ChannelInfo]) -> Result<(), FormatError> {
    if channels.len() > MAX_CHANNELS {
        return Err(FormatError::invalid(
            "channels",
            format!("{} channels, at most {MAX_CHANNELS}", channels.len()),
        ));
    }
    for (i, c) in channels.iter().enumerate() {
        c.validate()?;
        if channels[..i].iter().any(|o| o.name == c.name) {
            return Err(FormatError::invalid(
                "channels",
                format!("{:?} is listed twice", c.name),
            ));
        }
    }
    Ok(())
}

/// The most frequent of 8 values. Ties go to the smallest of the values tied. With `sparse`,
/// 0 counts only when all 8 are 0 (any other value beats it).
///
/// Why the smallest: a rule that depends on the values only, not on where in the 2x2x2 they
/// sit, gives the same parent whatever order the octant is read in, and is what a reader can
/// reproduce without knowing our loop order.
pub fn mode_of_8(values: [u64; 8], sparse: bool) -> u64 {
    // Each value's count by comparing it with all eight: 64 comparisons without branches,
    // which the compiler turns into a few vector compares (a sort of eight took several times
    // as long, and the groups that reach here are the boundaries of a material or label).
    let counts: [u32; 8] =
        std::array::from_fn(|i| values.iter().map(|&w| u32::from(w == values[i])).sum());
    // The winner is the largest key (count, then the smaller value): a maximum without
    // branches, where comparing value by value mispredicted. A sparse 0 gets key 0 and loses.
    let key = |v: u64, count: u32| (u128::from(count) << 64) | u128::from(u64::MAX - v);
    let best = values
        .iter()
        .zip(counts)
        .map(|(&v, count)| if sparse && v == 0 { 0 } else { key(v, count) })
        .max()
        .unwrap_or(0);
    // With `sparse` and all eight 0, every key is 0: the mode is 0.
    if best == 0 {
        0
    } else {
        u64::MAX - best as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mode_of_eight_by_hand() {
        // Five 3s beat three 7s.
        assert_eq!(mode_of_8([7, 3, 3, 7, 3, 7, 3, 3], false), 3);
        // 4 against 4: the smaller value.
        assert_eq!(mode_of_8([9, 2, 9, 2, 9, 2, 9, 2], false), 2);
        // 2-2-2-2: 1, 5, 6, 8 twice each: the smallest, 1.
        assert_eq!(mode_of_8([8, 6, 5, 1, 8, 6, 5, 1], false), 1);
        // All different: the smallest.
        assert_eq!(mode_of_8([8, 7, 6, 5, 4, 3, 2, 10], false), 2);
        // Six 0s win when 0 counts...
        assert_eq!(mode_of_8([0, 0, 0, 4, 0, 0, 4, 0], false), 0);
        // ...and lose when sparse: the one other value wins.
        assert_eq!(mode_of_8([0, 0, 0, 4, 0, 0, 4, 0], true), 4);
        assert_eq!(mode_of_8([0, 0, 0, 4, 0, 5, 5, 0], true), 5);
        // Sparse ties among the non-zero values: the smaller.
        assert_eq!(mode_of_8([0, 0, 0, 4, 0, 0, 5, 0], true), 4);
        assert_eq!(mode_of_8([0; 8], true), 0);
        assert_eq!(mode_of_8([u64::MAX; 8], false), u64::MAX);
    }

    /// Every group of eight values from {0, 1, 2} (6,561 of them), and random groups of wider
    /// values, against the rule counted another way: a map from value to count, the largest
    /// count, the smallest value among those with it.
    #[test]
    fn the_mode_of_eight_follows_the_rule_counted_by_a_map() {
        let by_map = |values: [u64; 8], sparse: bool| {
            let mut counts = std::collections::BTreeMap::new();
            for v in values.into_iter().filter(|&v| !(sparse && v == 0)) {
                *counts.entry(v).or_insert(0) += 1;
            }
            let most = counts.values().copied().max().unwrap_or(0);
            // BTreeMap iterates ascending: the first with the largest count is the smallest.
            counts
                .into_iter()
                .find(|&(_, c)| c == most)
                .map_or(0, |(v, _)| v)
        };
        let mut groups: Vec<[u64; 8]> = (0..3u64.pow(8))
            .map(|n| std::array::from_fn(|i| n / 3u64.pow(i as u32) % 3))
            .collect();
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        for _ in 0..10_000 {
            groups.push(std::array::from_fn(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                [0, 1, 5, u64::MAX, state % 7][(state >> 32) as usize % 5]
            }));
        }
        for g in groups {
            for sparse in [false, true] {
                assert_eq!(
                    mode_of_8(g, sparse),
                    by_map(g, sparse),
                    "{g:?} sparse {sparse}"
                );
            }
        }
    }

    #[test]
    fn channel_names_and_palettes_are_checked() {
        let ok = ChannelInfo {
            palette: vec!["#ff0000".into(), "#00Aa00".into()],
            ..ChannelInfo::new("material", VoxelType::U8)
        };
        assert!(ok.validate().is_ok());
        for name in ["", "density", "Material", "9lives", "a-b", &"x".repeat(33)] {
            assert!(
                ChannelInfo::new(name, VoxelType::U8).validate().is_err(),
                "{name:?}"
            );
        }
        let bad_colour = ChannelInfo {
            palette: vec!["red".into()],
            ..ChannelInfo::new("material", VoxelType::U8)
        };
        assert!(bad_colour.validate().is_err());
        let twice = [ok.clone(), ok];
        assert!(validate_channels(&twice).is_err());
        assert_eq!(parse_colour("#0a0B0c"), Some([10, 11, 12]));
    }
}
