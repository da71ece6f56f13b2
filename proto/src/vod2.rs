//! VOD 2 on-disk records, encoded and decoded over byte slices.
//!
//! The full byte layout, with the reasons behind it, is `docs/vod2.md`. In short:
//!
//! ```text
//! [0, 4096)        file header (fixed at creation, checksummed)
//! [4096, 8192)     header slot A  } the two switchable slots: each names the newest durable
//! [8192, 12288)    header slot B  } commit; written alternately, sequence number + checksum
//! [12288, ...)     append-only region: brick records, index checkpoints, commit records
//! ```
//!
//! All integers are little endian. Every decoder checks bounds, sizes and checksums and returns a
//! [`FormatError`] naming the problem; none panics on any input.

use crate::channel::ChannelInfo;
use crate::error::FormatError;
use crate::layout::{VolumeLayout, MAX_NODES};
use crate::voxel::VoxelType;
use xxhash_rust::xxh3::xxh3_64;

/// First four bytes of every VOD file (VOD 1 and VOD 2 alike), in file order.
pub const SIGNATURE: [u8; 4] = *b".VOD";
/// The `fileVersion` this module reads and writes.
pub const FORMAT_VERSION: u32 = 2;
/// Content hash algorithm fourcc: xxh3, 64 bits, of the decoded brick bytes.
pub const HASH_XH64: [u8; 4] = *b"XH64";
/// Size of the file header record.
pub const HEADER_LEN: usize = 128;
/// Size of the header page: the header and, after it, the channel table (revision 4).
pub const DATA_PAGE: usize = 4096;
/// Longest channel table: what the header page holds after the header.
pub const MAX_CHANNEL_TABLE: u32 = (DATA_PAGE - HEADER_LEN) as u32;
/// Offsets of the two header slots; each sits alone in its own 4 KiB page so that a torn write
/// of one can never damage the other.
pub const SLOT_OFFSETS: [u64; 2] = [4096, 8192];
/// Size of a header slot record: the 48 bytes every reader checks, then the appended-bytes check
/// of revision 2 (flag [`SLOT_APPENDED_CHECKED`]), which readers before it never read.
pub const SLOT_LEN: usize = 72;
/// Header slot flag (the u32 at offset 4): the slot carries [`AppendedCheck`], the checksum of
/// the bytes appended since the previous slot, and holds only if they match it. A writer sets
/// it when the slot and those bytes were made durable by one sync together.
pub const SLOT_APPENDED_CHECKED: u32 = 1;
/// Where the append-only region starts.
pub const DATA_START: u64 = 12288;
/// Size of the header in front of every stored brick payload of a u8 or u16 stream.
pub const BRICK_HEADER_LEN: usize = 24;
/// Size of the header in front of a brick payload of a u32 or u64 stream (revision 6): its
/// value range takes two u64 ([`RECORD_WIDE_RANGE`]).
pub const WIDE_BRICK_HEADER_LEN: usize = 40;
/// Brick record flag (header byte 13): the payload is followed by its checksum
/// ([`payload_check`], [`PAYLOAD_CHECK_LEN`] bytes), so that it can be verified without
/// decoding before it is sent as it is. Every record written since this revision of the format
/// has it; records written before have no flag and no checksum.
pub const RECORD_PAYLOAD_CHECKED: u8 = 1;
/// Brick record flag (header byte 13, revision 6): the record belongs to a u32 or u64 stream
/// and its header is [`WIDE_BRICK_HEADER_LEN`] bytes, the range two u64 at 16 and 24.
pub const RECORD_WIDE_RANGE: u8 = 2;
/// Size of the checksum that follows a checked payload.
pub const PAYLOAD_CHECK_LEN: usize = 4;
/// Size of a commit record without its changes.
pub const COMMIT_FIXED_LEN: usize = 56;
/// Bytes per change entry in a commit record: (node index, node entry).
pub const CHANGE_LEN: usize = 16;
/// Commit record flag (bytes 4..8, revision 3): a note follows the record's checksum (its
/// length as u32, the note, an xxh3 checksum of the record and the note).
pub const COMMIT_HAS_NOTE: u32 = 1;
/// Commit record flag (revision 5): the summary of each change's new entry follows the record
/// (after the note, if any): [`SUMMARY_LEN`] bytes per change, then an xxh3 checksum of the
/// record's bytes from its start.
pub const COMMIT_HAS_SUMMARIES: u32 = 2;
/// Commit record flag (revision 6): the summaries are [`WIDE_SUMMARY_LEN`] bytes each (the
/// file has a u32 or u64 channel).
pub const COMMIT_WIDE_SUMMARIES: u32 = 4;
/// Bytes per brick summary ([`BrickSummary`]): content hash, smallest and largest value.
pub const SUMMARY_LEN: usize = 12;
/// Bytes per brick summary in a file with a u32 or u64 channel (revision 6): the range is two
/// u64.
pub const WIDE_SUMMARY_LEN: usize = 24;
/// Chunk reference flag (byte 13, revision 5): the chunk's payload is followed by a summary
/// block ([`SUMMARY_BLOCK_HEADER_LEN`] bytes of header, then the encoded summaries) whose
/// length is the u16 at bytes 14..16.
pub const CHUNK_HAS_SUMMARIES: u8 = 1;
/// The header in front of a summary block: u64 xxh3 of the decoded summaries, u8 codec, seven
/// zero bytes.
pub const SUMMARY_BLOCK_HEADER_LEN: usize = 16;
/// Longest note a commit record may carry.
pub const MAX_NOTE_LEN: u32 = 4 << 20;
/// Bytes that frame a note: its length before it, the checksum after it.
pub const NOTE_FRAMING_LEN: usize = 12;
/// Size of a checkpoint's leading fields.
pub const CHECKPOINT_FIXED_LEN: usize = 24;
/// Index entries per checkpoint chunk (4 KiB of entries).
pub const CHUNK_ENTRIES: u64 = 512;
/// Header flag: edge bricks are padded with L on the right-hand side (always set; VOD 1 bit 1).
pub const FLAG_RIGHT_PADDING: u32 = 1 << 1;

const SLOT_MAGIC: [u8; 4] = *b"VSLT";
const COMMIT_MAGIC: [u8; 4] = *b"VCMT";
const CHECKPOINT_MAGIC: [u8; 4] = *b"VIDX";
const NODE_CONSTANT: u64 = 1 << 63;
/// The largest value a constant index entry holds: the entry's other 63 bits.
pub const MAX_CONSTANT: u64 = NODE_CONSTANT - 1;

/// The content hash of a decoded brick: xxh3-64 of its bytes (u16 little endian).
pub fn content_hash(bytes: &[u8]) -> u64 {
    xxh3_64(bytes)
}

/// The checksum stored after a brick payload: the low 32 bits of xxh3-64 of the stored
/// (compressed) bytes.
pub fn payload_check(payload: &[u8]) -> u32 {
    xxh3_64(payload) as u32
}

/// Bounds-checked little-endian reads from a record.
#[derive(Debug, Clone, Copy)]
pub struct Fields<'a> {
    what: &'static str,
    bytes: &'a [u8],
    base: u64,
}

impl<'a> Fields<'a> {
    /// A view of `bytes`, which sit at file offset `base` (for error messages).
    pub fn new(what: &'static str, bytes: &'a [u8], base: u64) -> Self {
        Fields { what, bytes, base }
    }

    /// `len` bytes at `off`.
    ///
    /// # Errors
    /// The range is outside the record.
    pub fn slice(&self, off: usize, len: usize) -> Result<&'a [u8], FormatError> {
        off.checked_add(len)
            .and_then(|end| self.bytes.get(off..end))
            .ok_or(FormatError::Truncated {
                what: self.what,
                offset: self.base + off as u64,
                needed: len as u64,
                available: self.bytes.len().saturating_sub(off) as u64,
            })
    }

    fn array<const N: usize>(&self, off: usize) -> Result<[u8; N], FormatError> {
        let s = self.slice(off, N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    /// The u16 at `off`.
    pub fn u16(&self, off: usize) -> Result<u16, FormatError> {
        Ok(u16::from_le_bytes(self.array(off)?))
    }
    /// The u32 at `off`.
    pub fn u32(&self, off: usize) -> Result<u32, FormatError> {
        Ok(u32::from_le_bytes(self.array(off)?))
    }
    /// The u64 at `off`.
    pub fn u64(&self, off: usize) -> Result<u64, FormatError> {
        Ok(u64::from_le_bytes(self.array(off)?))
    }
    /// The f32 at `off`.
    pub fn f32(&self, off: usize) -> Result<f32, FormatError> {
        Ok(f32::from_le_bytes(self.array(off)?))
    }
    /// The four bytes at `off`.
    pub fn fourcc(&self, off: usize) -> Result<[u8; 4], FormatError> {
        self.array(off)
    }

    /// Checks a fourcc at `off`.
    ///
    /// # Errors
    /// It differs from `expected`.
    pub fn magic(&self, off: usize, expected: [u8; 4]) -> Result<(), FormatError> {
        let found = self.fourcc(off)?;
        if found != expected {
            return Err(FormatError::BadMagic {
                what: self.what,
                expected,
                found,
            });
        }
        Ok(())
    }

    /// Checks that the u64 at `stored_at` equals xxh3 of bytes `[0, stored_at)`.
    ///
    /// # Errors
    /// The record is truncated or the checksum differs.
    pub fn checksum(&self, stored_at: usize) -> Result<(), FormatError> {
        let stored = self.u64(stored_at)?;
        let computed = xxh3_64(self.slice(0, stored_at)?);
        if stored != computed {
            return Err(FormatError::Checksum {
                what: self.what,
                offset: self.base,
                stored,
                computed,
            });
        }
        Ok(())
    }
}

fn put(buf: &mut [u8], off: usize, bytes: &[u8]) {
    buf[off..off + bytes.len()].copy_from_slice(bytes);
}

fn seal(buf: &mut [u8], stored_at: usize) {
    let sum = xxh3_64(&buf[..stored_at]);
    put(buf, stored_at, &sum.to_le_bytes());
}

/// The file header: the volume's shape, fixed when the file is created.
#[derive(Debug, Clone, PartialEq)]
pub struct FileHeader {
    /// Dimensions, brick edge and voxel type.
    pub layout: VolumeLayout,
    /// World size of one level-0 voxel.
    pub voxel_scale: [f32; 3],
    /// Reserved flags (0).
    pub flags: u32,
    /// The attribute channels beside density (revision 4), in stream order: channel `i + 1`.
    pub channels: Vec<ChannelInfo>,
}

impl FileHeader {
    /// The header of a new file.
    pub fn new(layout: VolumeLayout, voxel_scale: [f32; 3]) -> Self {
        FileHeader {
            layout,
            voxel_scale,
            flags: FLAG_RIGHT_PADDING,
            channels: Vec::new(),
        }
    }

    /// The header of a new file with attribute channels beside density.
    ///
    /// # Errors
    /// A channel is invalid (name, palette), there are too many, or their table does not fit
    /// in the header page.
    pub fn with_channels(
        layout: VolumeLayout,
        voxel_scale: [f32; 3],
        channels: Vec<ChannelInfo>,
    ) -> Result<Self, FormatError> {
        crate::channel::validate_channels(&channels)?;
        let header = FileHeader {
            channels,
            ..FileHeader::new(layout, voxel_scale)
        };
        let table = header.channel_table().map_or(0, |t| t.len());
        if table > MAX_CHANNEL_TABLE as usize {
            return Err(FormatError::invalid(
                "channel table",
                format!("{table} bytes, the header page holds {MAX_CHANNEL_TABLE} (shorten the palettes)"),
            ));
        }
        if header
            .layout
            .node_count()
            .saturating_mul(1 + header.channels.len() as u64)
            > MAX_NODES
        {
            return Err(FormatError::invalid(
                "channels",
                format!(
                    "{} streams of {} bricks each are too many",
                    1 + header.channels.len(),
                    header.layout.node_count()
                ),
            ));
        }
        Ok(header)
    }

    /// The layout of stream `stream`'s pyramid: density's shape with the stream's value type.
    pub fn stream_layout(&self, stream: usize) -> Option<VolumeLayout> {
        match stream {
            0 => Some(self.layout.clone()),
            s => self
                .channels
                .get(s - 1)
                .map(|c| self.layout.with_voxel_type(c.voxel_type)),
        }
    }

    /// Whether the file's brick summaries are wide ([`WIDE_SUMMARY_LEN`]): it has a u32 or
    /// u64 channel (revision 6).
    pub fn wide_summaries(&self) -> bool {
        self.channels.iter().any(|c| c.voxel_type.is_wide())
    }

    /// Index entries of the whole file: one pyramid per stream (density, then each channel).
    pub fn node_count(&self) -> u64 {
        self.layout.node_count() * (1 + self.channels.len() as u64)
    }

    /// The stream (0 density, `i + 1` channel `i`) holding the node `node` of the file's index,
    /// with the voxel type of its values; `None` past the last stream.
    pub fn stream_of(&self, node: u64) -> Option<(usize, VoxelType)> {
        let stream = usize::try_from(node / self.layout.node_count()).ok()?;
        match stream {
            0 => Some((0, self.layout.voxel_type())),
            s => self.channels.get(s - 1).map(|c| (s, c.voxel_type)),
        }
    }

    /// The stream of the channel named `name` (1 for the first attribute channel).
    pub fn stream_named(&self, name: &str) -> Option<usize> {
        self.channels
            .iter()
            .position(|c| c.name == name)
            .map(|i| i + 1)
    }

    /// The bytes of the header page: the header and, when there are attribute channels, the
    /// channel table after it (`docs/vod2.md`, revision 4).
    pub fn encode_page(&self) -> Vec<u8> {
        let mut page = vec![0u8; DATA_PAGE];
        page[..HEADER_LEN].copy_from_slice(&self.encode());
        if let Some(table) = self.channel_table() {
            // with_channels made sure it fits; a header built otherwise gets no table, and
            // reading it back fails rather than reading a cut one.
            if let Some(room) = page.get_mut(HEADER_LEN..HEADER_LEN + table.len()) {
                room.copy_from_slice(&table);
            }
        }
        page
    }

    /// The channel table: u32 JSON length, the JSON, xxh3-64 of both.
    fn channel_table(&self) -> Option<Vec<u8>> {
        if self.channels.is_empty() {
            return None;
        }
        // Serializing plain data to a Vec cannot fail.
        let json = serde_json::to_vec(&self.channels).unwrap_or_default();
        let mut t = Vec::with_capacity(json.len() + 12);
        t.extend_from_slice(&(json.len() as u32).to_le_bytes());
        t.extend_from_slice(&json);
        let sum = xxh3_64(&t);
        t.extend_from_slice(&sum.to_le_bytes());
        Some(t)
    }

    /// The header's bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        let l = &self.layout;
        put(&mut b, 0, &SIGNATURE);
        put(&mut b, 4, &FORMAT_VERSION.to_le_bytes());
        put(&mut b, 8, &(HEADER_LEN as u32).to_le_bytes());
        put(&mut b, 12, &self.flags.to_le_bytes());
        for (i, d) in l.dims().iter().enumerate() {
            put(&mut b, 16 + 4 * i, &d.to_le_bytes());
        }
        put(&mut b, 28, &l.brick().to_le_bytes());
        put(&mut b, 32, &l.voxel_type().bits().to_le_bytes());
        put(&mut b, 36, &(l.levels() as u32).to_le_bytes());
        for (i, s) in self.voxel_scale.iter().enumerate() {
            put(&mut b, 40 + 4 * i, &s.to_le_bytes());
        }
        put(&mut b, 52, &HASH_XH64);
        put(&mut b, 56, &(1 + self.channels.len() as u32).to_le_bytes());
        let table_len = self.channel_table().map_or(0, |t| t.len() as u32);
        put(&mut b, 60, &table_len.to_le_bytes());
        seal(&mut b, HEADER_LEN - 8);
        b
    }

    /// # Errors
    /// Bad signature, version, checksum, or a shape that [`VolumeLayout::new`] rejects.
    pub fn decode(bytes: &[u8]) -> Result<Self, FormatError> {
        let f = Fields::new("file header", bytes, 0);
        f.magic(0, SIGNATURE)?;
        let version = f.u32(4)?;
        if version != FORMAT_VERSION {
            return Err(FormatError::Unsupported {
                what: "file version",
                detail: format!("{version} (this reader handles VOD {FORMAT_VERSION})"),
            });
        }
        let header_len = f.u32(8)?;
        if header_len as usize != HEADER_LEN {
            return Err(FormatError::invalid(
                "file header",
                format!("header length {header_len}, expected {HEADER_LEN}"),
            ));
        }
        f.checksum(HEADER_LEN - 8)?;
        let flags = f.u32(12)?;
        let dims = [f.u32(16)?, f.u32(20)?, f.u32(24)?];
        let brick = f.u32(28)?;
        let bits = f.u32(32)?;
        let voxel_type = VoxelType::from_bits(bits).ok_or_else(|| FormatError::Unsupported {
            what: "voxel size",
            detail: format!("{bits} bits per voxel"),
        })?;
        let layout = VolumeLayout::new(dims, brick, voxel_type)?;
        let levels = f.u32(36)?;
        if levels != layout.levels() as u32 {
            return Err(FormatError::invalid(
                "file header",
                format!("{levels} levels stored, the shape has {}", layout.levels()),
            ));
        }
        let voxel_scale = [f.f32(40)?, f.f32(44)?, f.f32(48)?];
        if voxel_scale.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(FormatError::invalid(
                "file header",
                format!("voxel scale {voxel_scale:?} is not positive and finite"),
            ));
        }
        let hash = f.fourcc(52)?;
        if hash != HASH_XH64 {
            return Err(FormatError::Unsupported {
                what: "hash algorithm",
                detail: format!("{:?}", String::from_utf8_lossy(&hash)),
            });
        }
        let streams = f.u32(56)?;
        let table_len = f.u32(60)?;
        let channels = match (streams, table_len) {
            (1, 0) => Vec::new(),
            (2..=8, 13..=MAX_CHANNEL_TABLE) => {
                let rest = bytes.get(HEADER_LEN..).unwrap_or_default();
                let table = Fields::new("channel table", rest, HEADER_LEN as u64);
                table.checksum(table_len as usize - 8)?;
                let json_len = table.u32(0)?;
                if json_len as usize + 12 != table_len as usize {
                    return Err(FormatError::invalid(
                        "channel table",
                        format!("{json_len} bytes of JSON in a table of {table_len}"),
                    ));
                }
                let json = table.slice(4, json_len as usize)?;
                let channels: Vec<ChannelInfo> = serde_json::from_slice(json).map_err(|e| {
                    FormatError::invalid("channel table", format!("not a channel list: {e}"))
                })?;
                crate::channel::validate_channels(&channels)?;
                if channels.len() as u32 + 1 != streams {
                    return Err(FormatError::invalid(
                        "channel table",
                        format!(
                            "{} channels listed, the header counts {streams} streams",
                            channels.len()
                        ),
                    ));
                }
                channels
            }
            _ => {
                return Err(FormatError::Unsupported {
                    what: "channel count",
                    detail: format!("{streams} streams with a channel table of {table_len} bytes"),
                })
            }
        };
        if layout.node_count().saturating_mul(streams as u64) > MAX_NODES {
            return Err(FormatError::invalid(
                "file header",
                format!(
                    "{streams} streams of {} bricks each are too many",
                    layout.node_count()
                ),
            ));
        }
        Ok(FileHeader {
            layout,
            voxel_scale,
            flags,
            channels,
        })
    }
}

/// A header slot: which commit is the newest durable one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeaderSlot {
    /// Increases by one with every slot write; the valid slot with the highest wins.
    pub seq: u64,
    /// File offset of the head commit record.
    pub commit: u64,
    /// File length covered by that commit: nothing beyond it is referenced.
    pub committed_len: u64,
    /// The head commit's version number.
    pub version: u64,
    /// Set when the slot was synced together with the bytes it names (one `fdatasync` for
    /// both): the checksum those bytes must match for the slot to hold.
    pub appended: Option<AppendedCheck>,
}

/// The bytes `[from, committed_len)` a slot names beyond the previous slot, and their xxh3-64.
/// A crash may leave the slot on disk without all of them; the checksum tells.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AppendedCheck {
    /// The previous slot's committed length, where the checked bytes start.
    pub from: u64,
    /// xxh3-64 of the bytes `[from, committed_len)`.
    pub checksum: u64,
}

/// Where a slot's own checksums sit: the first covers the fields every reader knows, the
/// second the whole record with the appended-bytes check.
const SLOT_BASE_CHECK_AT: usize = 40;
const SLOT_FULL_CHECK_AT: usize = SLOT_LEN - 8;

impl HeaderSlot {
    /// The slot's bytes, checksums included.
    pub fn encode(&self) -> [u8; SLOT_LEN] {
        let mut b = [0u8; SLOT_LEN];
        put(&mut b, 0, &SLOT_MAGIC);
        put(&mut b, 8, &self.seq.to_le_bytes());
        put(&mut b, 16, &self.commit.to_le_bytes());
        put(&mut b, 24, &self.committed_len.to_le_bytes());
        put(&mut b, 32, &self.version.to_le_bytes());
        if let Some(check) = self.appended {
            put(&mut b, 4, &SLOT_APPENDED_CHECKED.to_le_bytes());
            put(&mut b, 48, &check.from.to_le_bytes());
            put(&mut b, 56, &check.checksum.to_le_bytes());
        }
        seal(&mut b, SLOT_BASE_CHECK_AT);
        if self.appended.is_some() {
            seal(&mut b, SLOT_FULL_CHECK_AT);
        }
        b
    }

    /// Decodes the record alone. A slot with an appended-bytes check holds only if those
    /// bytes match it too, which the caller checks against the file.
    ///
    /// # Errors
    /// Bad magic or checksum (a slot never written, or torn), unknown flags, or offsets that
    /// do not fit.
    pub fn decode(bytes: &[u8], base: u64) -> Result<Self, FormatError> {
        let f = Fields::new("header slot", bytes, base);
        f.magic(0, SLOT_MAGIC)?;
        f.checksum(SLOT_BASE_CHECK_AT)?;
        let flags = f.u32(4)?;
        if flags & !SLOT_APPENDED_CHECKED != 0 {
            return Err(FormatError::invalid(
                "header slot",
                format!("unknown flags {flags:#x}"),
            ));
        }
        let appended = if flags & SLOT_APPENDED_CHECKED != 0 {
            f.checksum(SLOT_FULL_CHECK_AT)?;
            Some(AppendedCheck {
                from: f.u64(48)?,
                checksum: f.u64(56)?,
            })
        } else {
            None
        };
        let slot = HeaderSlot {
            seq: f.u64(8)?,
            commit: f.u64(16)?,
            committed_len: f.u64(24)?,
            version: f.u64(32)?,
            appended,
        };
        if slot.commit < DATA_START
            || slot
                .commit
                .checked_add(COMMIT_FIXED_LEN as u64)
                .is_none_or(|end| end > slot.committed_len)
        {
            return Err(FormatError::invalid(
                "header slot",
                format!(
                    "commit offset {} outside the committed region [{DATA_START}, {})",
                    slot.commit, slot.committed_len
                ),
            ));
        }
        // The head commit is one of the appended records.
        if let Some(check) = appended {
            if check.from < DATA_START || check.from > slot.commit {
                return Err(FormatError::invalid(
                    "header slot",
                    format!(
                        "appended bytes from {} do not hold the head commit at {} (and start at {DATA_START} or later)",
                        check.from, slot.commit
                    ),
                ));
            }
        }
        Ok(slot)
    }
}

/// How a stored brick's payload is encoded. (The third codec, constant, has no payload at all: it
/// lives in the index entry, see [`NodeEntry::Constant`].)
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Codec {
    /// The decoded bytes as they are.
    Raw = 0,
    /// An lz4 block (lz4_flex block format, no frame); decodes to exactly one brick.
    Lz4 = 1,
    /// A zstd frame; decodes to exactly one brick. Denser than lz4 (what the compression goals
    /// need) and still decoded at over 1 GB/s; HTTP can send it as `Content-Encoding: zstd`.
    Zstd = 2,
    /// A zstd frame of the brick's distinct values (its palette) and, per voxel, the index of
    /// its value in the palette (revision 6, u32 and u64 streams only: `docs/vod2.md`).
    Palette = 3,
}

impl Codec {
    /// The codec's name as the command line and reports spell it.
    pub fn name(self) -> &'static str {
        match self {
            Codec::Raw => "raw",
            Codec::Lz4 => "lz4",
            Codec::Zstd => "zstd",
            Codec::Palette => "palette",
        }
    }
}

/// The header in front of a stored brick's payload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BrickHeader {
    /// [`content_hash`] of the decoded brick.
    pub hash: u64,
    /// Payload bytes that follow the header.
    pub stored_len: u32,
    /// How the payload is encoded.
    pub codec: Codec,
    /// Smallest and largest voxel value of the brick (answers "can this hold a surface?"
    /// without decoding).
    pub min: u64,
    /// The largest voxel value.
    pub max: u64,
    /// Whether the payload is followed by its checksum ([`RECORD_PAYLOAD_CHECKED`]); false
    /// only in records written before payload checksums.
    pub checked: bool,
    /// Whether the record belongs to a u32 or u64 stream ([`RECORD_WIDE_RANGE`]): its header
    /// is [`WIDE_BRICK_HEADER_LEN`] bytes.
    pub wide: bool,
}

impl BrickHeader {
    /// Bytes of the header of a record of a stream of `voxel_type`.
    pub const fn len_for(voxel_type: VoxelType) -> usize {
        if voxel_type.is_wide() {
            WIDE_BRICK_HEADER_LEN
        } else {
            BRICK_HEADER_LEN
        }
    }

    /// Bytes of this header.
    pub const fn header_len(&self) -> usize {
        if self.wide {
            WIDE_BRICK_HEADER_LEN
        } else {
            BRICK_HEADER_LEN
        }
    }

    /// Bytes of the whole record: header, payload and, when checked, the payload's checksum.
    pub fn record_len(&self) -> u64 {
        let check = if self.checked { PAYLOAD_CHECK_LEN } else { 0 };
        (self.header_len() + check) as u64 + self.stored_len as u64
    }

    /// The header's bytes.
    ///
    /// # Panics
    /// A narrow header (`wide` false) with a range beyond u16.
    pub fn encode(&self) -> Vec<u8> {
        let mut b = vec![0u8; self.header_len()];
        put(&mut b, 0, &self.hash.to_le_bytes());
        put(&mut b, 8, &self.stored_len.to_le_bytes());
        b[12] = self.codec as u8;
        if self.checked {
            b[13] |= RECORD_PAYLOAD_CHECKED;
        }
        let check_at = if self.wide {
            b[13] |= RECORD_WIDE_RANGE;
            put(&mut b, 16, &self.min.to_le_bytes());
            put(&mut b, 24, &self.max.to_le_bytes());
            32
        } else {
            let narrow = |v: u64| u16::try_from(v).expect("a u8 or u16 stream's range");
            put(&mut b, 14, &narrow(self.min).to_le_bytes());
            put(&mut b, 16, &narrow(self.max).to_le_bytes());
            20
        };
        let check = xxh3_64(&b[..check_at]) as u32;
        put(&mut b, check_at, &check.to_le_bytes());
        b
    }

    /// Decodes and validates a brick header against the volume's shape: the payload length must
    /// be plausible for the codec and the brick size.
    ///
    /// # Errors
    /// Checksum mismatch, unknown codec or flags, impossible length or value range.
    pub fn decode(bytes: &[u8], base: u64, layout: &VolumeLayout) -> Result<Self, FormatError> {
        let f = Fields::new("brick header", bytes, base);
        let wide = layout.voxel_type().is_wide();
        let check_at = if wide { 32 } else { 20 };
        let stored = f.u32(check_at)?;
        let computed = xxh3_64(f.slice(0, check_at)?) as u32;
        if stored != computed {
            return Err(FormatError::Checksum {
                what: "brick header",
                offset: base,
                stored: stored as u64,
                computed: computed as u64,
            });
        }
        let codec = match f.slice(12, 1)?[0] {
            0 => Codec::Raw,
            1 => Codec::Lz4,
            2 => Codec::Zstd,
            3 if wide => Codec::Palette,
            other => {
                return Err(FormatError::Unsupported {
                    what: "brick codec",
                    detail: format!("{other} at offset {base}"),
                })
            }
        };
        let flags = f.slice(13, 1)?[0];
        let wide_flag = if wide { RECORD_WIDE_RANGE } else { 0 };
        if flags & !RECORD_PAYLOAD_CHECKED != wide_flag {
            return Err(FormatError::Unsupported {
                what: "brick record flags",
                detail: format!(
                    "{flags:#04x} at offset {base} in a stream of {}",
                    layout.voxel_type()
                ),
            });
        }
        let (min, max) = if wide {
            (f.u64(16)?, f.u64(24)?)
        } else {
            (u64::from(f.u16(14)?), u64::from(f.u16(16)?))
        };
        let h = BrickHeader {
            hash: f.u64(0)?,
            stored_len: f.u32(8)?,
            codec,
            min,
            max,
            checked: flags & RECORD_PAYLOAD_CHECKED != 0,
            wide,
        };
        let brick_bytes = layout.brick_bytes() as u64;
        let len_ok = match codec {
            Codec::Raw => h.stored_len as u64 == brick_bytes,
            // An lz4 block of n bytes decodes to at most ~255 * n bytes; anything longer than the
            // raw brick would have been stored raw.
            Codec::Lz4 | Codec::Zstd | Codec::Palette => {
                h.stored_len > 0 && (h.stored_len as u64) < brick_bytes
            }
        };
        let high = layout.voxel_type().max_value();
        if !len_ok || h.min > h.max || h.max > high {
            return Err(FormatError::invalid(
                "brick header",
                format!(
                    "at offset {base}: codec {} with {} payload bytes, range [{}, {}] (brick of {brick_bytes} bytes, max value {high})",
                    codec.name(),
                    h.stored_len,
                    h.min,
                    h.max
                ),
            ));
        }
        Ok(h)
    }
}

/// One entry of the pyramidal index: what a brick of the volume is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NodeEntry {
    /// Every voxel holds this value; no payload is stored (the "constant" codec). At most
    /// [`MAX_CONSTANT`]: a u64 brick of one larger value is stored as a record.
    Constant(u64),
    /// A brick record (header and payload) at this file offset.
    Stored(u64),
}

impl NodeEntry {
    /// Whether a raw index entry is a constant (its flag bit set), before it is decoded.
    pub fn is_constant(raw: u64) -> bool {
        raw & NODE_CONSTANT != 0
    }

    /// The entry as stored in the index.
    pub fn encode(self) -> u64 {
        match self {
            NodeEntry::Constant(v) => {
                // Writers store a larger u64 value as a record (see MAX_CONSTANT): a constant
                // past it would lose its top bit to the flag.
                assert!(
                    v <= MAX_CONSTANT,
                    "constant {v} does not fit an index entry"
                );
                NODE_CONSTANT | v
            }
            NodeEntry::Stored(off) => off,
        }
    }

    /// # Errors
    /// A constant outside the voxel type's range or with stray bits, or an offset before the
    /// data region or past the committed length.
    pub fn decode(
        raw: u64,
        voxel_type: VoxelType,
        committed_len: u64,
    ) -> Result<Self, FormatError> {
        if raw & NODE_CONSTANT != 0 {
            let v = raw & !NODE_CONSTANT;
            if v > voxel_type.max_value() {
                return Err(FormatError::invalid(
                    "index entry",
                    format!("constant {v} out of range for {voxel_type}"),
                ));
            }
            return Ok(NodeEntry::Constant(v));
        }
        if raw < DATA_START || raw.saturating_add(BRICK_HEADER_LEN as u64) > committed_len {
            return Err(FormatError::invalid(
                "index entry",
                format!(
                    "brick offset {raw} outside the data region [{DATA_START}, {committed_len})"
                ),
            ));
        }
        Ok(NodeEntry::Stored(raw))
    }
}

/// What a client choosing bricks needs to know of one (revision 5): its content hash and value
/// range, the same three values as its record's header, kept in the index (checkpoint chunks
/// and commit records) so that a level grid is answered without reading any brick record.
///
/// A constant entry needs none (its value is all three): its summary is stored as zeros and
/// never read. Encoded in [`SUMMARY_LEN`] bytes (u16 range), or [`WIDE_SUMMARY_LEN`] in a
/// file with a u32 or u64 channel (u64 range, revision 6), for every stream of that file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub struct BrickSummary {
    /// [`content_hash`] of the decoded brick.
    pub hash: u64,
    /// The smallest voxel value.
    pub min: u64,
    /// The largest voxel value.
    pub max: u64,
}

impl BrickSummary {
    /// The summary a brick record's header gives.
    pub fn of_header(h: &BrickHeader) -> Self {
        BrickSummary {
            hash: h.hash,
            min: h.min,
            max: h.max,
        }
    }

    /// Bytes of one summary: [`WIDE_SUMMARY_LEN`] when `wide`, else [`SUMMARY_LEN`].
    pub const fn encoded_len(wide: bool) -> usize {
        if wide {
            WIDE_SUMMARY_LEN
        } else {
            SUMMARY_LEN
        }
    }

    /// The summary's bytes: u64 hash, then u16 min and max, or u64 min and max when `wide`.
    ///
    /// # Panics
    /// A range beyond u16 when not `wide`.
    pub fn encode_into(self, out: &mut Vec<u8>, wide: bool) {
        out.extend_from_slice(&self.hash.to_le_bytes());
        if wide {
            out.extend_from_slice(&self.min.to_le_bytes());
            out.extend_from_slice(&self.max.to_le_bytes());
        } else {
            let narrow = |v: u64| u16::try_from(v).expect("a u8 or u16 stream's range");
            out.extend_from_slice(&narrow(self.min).to_le_bytes());
            out.extend_from_slice(&narrow(self.max).to_le_bytes());
        }
    }

    /// Decodes one summary from its bytes (`bytes` shorter than [`BrickSummary::encoded_len`] reads
    /// as zeros).
    pub fn decode(bytes: &[u8], wide: bool) -> Self {
        let mut b = [0u8; WIDE_SUMMARY_LEN];
        let n = bytes.len().min(Self::encoded_len(wide));
        b[..n].copy_from_slice(&bytes[..n]);
        let u64_at = |at: usize| u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"));
        let u16_at = |at: usize| u64::from(u16::from_le_bytes([b[at], b[at + 1]]));
        BrickSummary {
            hash: u64_at(0),
            min: if wide { u64_at(8) } else { u16_at(8) },
            max: if wide { u64_at(16) } else { u16_at(10) },
        }
    }

    /// Encodes summaries one after another.
    pub fn encode_all(summaries: &[BrickSummary], wide: bool) -> Vec<u8> {
        let mut out = Vec::with_capacity(summaries.len() * Self::encoded_len(wide));
        for s in summaries {
            s.encode_into(&mut out, wide);
        }
        out
    }

    /// Decodes every whole summary of `bytes`.
    pub fn decode_all(bytes: &[u8], wide: bool) -> Vec<BrickSummary> {
        bytes
            .chunks_exact(Self::encoded_len(wide))
            .map(|b| Self::decode(b, wide))
            .collect()
    }

    /// Checks the value range against the stream's voxel type (`min <= max <= high`), as a
    /// brick header's is: a summary of a stored brick that fails it is damage.
    ///
    /// # Errors
    /// The range is impossible; `what` and `offset` name where it was read.
    pub fn validate(
        self,
        voxel_type: VoxelType,
        what: &'static str,
        offset: u64,
    ) -> Result<Self, FormatError> {
        if self.min > self.max || self.max > voxel_type.max_value() {
            return Err(FormatError::invalid(
                what,
                format!(
                    "at offset {offset}: range [{}, {}] (max value {})",
                    self.min,
                    self.max,
                    voxel_type.max_value()
                ),
            ));
        }
        Ok(self)
    }
}

/// The fixed part of a commit record. On disk it is followed by `n_changes` pairs of
/// (node index u64, [`NodeEntry`] u64) and an xxh3 checksum of everything before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CommitHeader {
    /// The version this commit makes.
    pub version: u64,
    /// Offset of the previous commit record, 0 for the first.
    pub parent: u64,
    /// When it was committed (Unix milliseconds).
    pub timestamp_ms: u64,
    /// Offset of an index checkpoint holding the full index after this commit, or 0 when the
    /// index is the parent's with this commit's changes applied.
    pub checkpoint: u64,
    /// Index changes that follow the fixed part.
    pub n_changes: u64,
    /// Bytes of the note that follows the record (revision 3), 0 for none.
    pub note_len: u32,
    /// Whether the summaries of the changes' entries follow (revision 5).
    pub summaries: bool,
    /// Whether those summaries are wide ([`COMMIT_WIDE_SUMMARIES`], revision 6: the file has a
    /// u32 or u64 channel).
    pub wide_summaries: bool,
}

impl CommitHeader {
    /// Bytes of the record without its note: what readers before revision 3 read.
    pub fn record_len(n_changes: u64) -> u64 {
        COMMIT_FIXED_LEN as u64 + n_changes * CHANGE_LEN as u64
    }

    /// Bytes of the record with its note, if it has one, without the summaries.
    fn len_with_note(&self) -> u64 {
        let note = if self.note_len > 0 {
            NOTE_FRAMING_LEN as u64 + u64::from(self.note_len)
        } else {
            0
        };
        Self::record_len(self.n_changes) + note
    }

    /// Bytes of the section of summaries (revision 5) for `n_changes` changes: the summaries
    /// and their checksum.
    pub fn summaries_len(n_changes: u64, wide: bool) -> u64 {
        n_changes * BrickSummary::encoded_len(wide) as u64 + 8
    }

    /// Bytes of the whole record: with its note and its summaries, if it has them.
    pub fn total_len(&self) -> u64 {
        let summaries = if self.summaries {
            Self::summaries_len(self.n_changes, self.wide_summaries)
        } else {
            0
        };
        self.len_with_note() + summaries
    }

    /// Encodes the record with its changes; when `note` is not empty, the note after it; when
    /// `summaries` is given (one per change, `self.summaries` set), the summaries after that.
    pub fn encode(
        &self,
        changes: &[(u64, NodeEntry)],
        note: &[u8],
        summaries: Option<&[BrickSummary]>,
    ) -> Vec<u8> {
        assert_eq!(changes.len() as u64, self.n_changes);
        assert_eq!(note.len() as u64, u64::from(self.note_len));
        assert_eq!(summaries.is_some(), self.summaries);
        assert!(summaries.is_none_or(|s| s.len() == changes.len()));
        let len = Self::record_len(self.n_changes) as usize;
        let mut b = vec![0u8; len];
        put(&mut b, 0, &COMMIT_MAGIC);
        let mut flags = 0;
        if !note.is_empty() {
            flags |= COMMIT_HAS_NOTE;
        }
        if summaries.is_some() {
            flags |= COMMIT_HAS_SUMMARIES;
            if self.wide_summaries {
                flags |= COMMIT_WIDE_SUMMARIES;
            }
        }
        put(&mut b, 4, &flags.to_le_bytes());
        put(&mut b, 8, &self.version.to_le_bytes());
        put(&mut b, 16, &self.parent.to_le_bytes());
        put(&mut b, 24, &self.timestamp_ms.to_le_bytes());
        put(&mut b, 32, &self.checkpoint.to_le_bytes());
        put(&mut b, 40, &self.n_changes.to_le_bytes());
        for (i, (node, entry)) in changes.iter().enumerate() {
            let at = 48 + i * CHANGE_LEN;
            put(&mut b, at, &node.to_le_bytes());
            put(&mut b, at + 8, &entry.encode().to_le_bytes());
        }
        seal(&mut b, len - 8);
        if !note.is_empty() {
            b.extend_from_slice(&self.note_len.to_le_bytes());
            b.extend_from_slice(note);
            b.extend_from_slice(&[0; 8]);
            let end = b.len();
            seal(&mut b, end - 8);
        }
        if let Some(summaries) = summaries {
            b.extend_from_slice(&BrickSummary::encode_all(summaries, self.wide_summaries));
            b.extend_from_slice(&[0; 8]);
            let end = b.len();
            seal(&mut b, end - 8);
        }
        b
    }

    /// Reads the record at `base`; `avail` is every byte from `base` to the end of the
    /// committed region. Returns the header and the record's bytes without its note (checksums
    /// verified, the note's too: [`CommitHeader::note`] reads it).
    ///
    /// Flag bits other than [`COMMIT_HAS_NOTE`] and [`COMMIT_HAS_SUMMARIES`] are ignored, as
    /// readers before revision 3 ignored every flag: a later revision may add what this reader
    /// need not know.
    ///
    /// # Errors
    /// Bad magic, truncation, checksum mismatch, or a change count or note length the region
    /// cannot hold.
    pub fn decode(avail: &[u8], base: u64) -> Result<(Self, &[u8]), FormatError> {
        let f = Fields::new("commit record", avail, base);
        f.magic(0, COMMIT_MAGIC)?;
        let n_changes = f.u64(40)?;
        let max_changes =
            (avail.len() as u64).saturating_sub(COMMIT_FIXED_LEN as u64) / CHANGE_LEN as u64;
        if n_changes > max_changes {
            return Err(FormatError::Truncated {
                what: "commit record",
                offset: base,
                needed: n_changes.saturating_mul(CHANGE_LEN as u64),
                available: avail.len() as u64,
            });
        }
        let len = Self::record_len(n_changes) as usize;
        let record = f.slice(0, len)?;
        Fields::new("commit record", record, base).checksum(len - 8)?;
        let note_len = if f.u32(4)? & COMMIT_HAS_NOTE != 0 {
            let note_len = f.u32(len)?;
            if note_len == 0 || note_len > MAX_NOTE_LEN {
                return Err(FormatError::invalid(
                    "commit record",
                    format!("at {base}: a note of {note_len} bytes (1..={MAX_NOTE_LEN} expected)"),
                ));
            }
            let total = len + NOTE_FRAMING_LEN + note_len as usize;
            Fields::new("commit note", f.slice(0, total)?, base).checksum(total - 8)?;
            note_len
        } else {
            0
        };
        let mut h = CommitHeader {
            version: f.u64(8)?,
            parent: f.u64(16)?,
            timestamp_ms: f.u64(24)?,
            checkpoint: f.u64(32)?,
            n_changes,
            note_len,
            summaries: false,
            wide_summaries: false,
        };
        let flags = f.u32(4)?;
        if flags & COMMIT_HAS_SUMMARIES != 0 {
            let wide = flags & COMMIT_WIDE_SUMMARIES != 0;
            // n_changes is bounded by the region above, so this cannot overflow.
            let total = (h.len_with_note() + Self::summaries_len(n_changes, wide)) as usize;
            Fields::new("commit summaries", f.slice(0, total)?, base).checksum(total - 8)?;
            h.summaries = true;
            h.wide_summaries = wide;
        }
        if h.parent >= base || (h.parent != 0 && h.parent < DATA_START) {
            return Err(FormatError::invalid(
                "commit record",
                format!("at {base}: parent offset {} does not precede it", h.parent),
            ));
        }
        if h.checkpoint >= base || (h.checkpoint != 0 && h.checkpoint < DATA_START) {
            return Err(FormatError::invalid(
                "commit record",
                format!(
                    "at {base}: checkpoint offset {} does not precede it",
                    h.checkpoint
                ),
            ));
        }
        if h.parent == 0 && h.checkpoint == 0 {
            return Err(FormatError::invalid(
                "commit record",
                format!("at {base}: neither a parent nor a checkpoint"),
            ));
        }
        Ok((h, record))
    }

    /// The note of the record `avail` starts with, as [`CommitHeader::decode`] checked it
    /// (`self` is what it returned); empty when it has none.
    pub fn note<'a>(&self, avail: &'a [u8]) -> &'a [u8] {
        if self.note_len == 0 {
            return &[];
        }
        let at = Self::record_len(self.n_changes) as usize + 4;
        avail
            .get(at..at + self.note_len as usize)
            .unwrap_or_default()
    }

    /// The summaries of the changes of the record `avail` starts with (revision 5), one per
    /// change in order, as [`CommitHeader::decode`] checked them; `None` when it has none.
    pub fn summaries_in(&self, avail: &[u8]) -> Option<Vec<BrickSummary>> {
        if !self.summaries {
            return None;
        }
        let at = self.len_with_note() as usize;
        let len = self.n_changes as usize * BrickSummary::encoded_len(self.wide_summaries);
        avail
            .get(at..at + len)
            .map(|b| BrickSummary::decode_all(b, self.wide_summaries))
    }

    /// The (node, raw entry) pairs of a record returned by [`CommitHeader::decode`].
    pub fn changes(record: &[u8]) -> impl Iterator<Item = (u64, u64)> + '_ {
        let body = &record[48..record.len() - 8];
        body.chunks_exact(CHANGE_LEN).map(|c| {
            let mut n = [0u8; 8];
            let mut e = [0u8; 8];
            n.copy_from_slice(&c[..8]);
            e.copy_from_slice(&c[8..]);
            (u64::from_le_bytes(n), u64::from_le_bytes(e))
        })
    }
}

/// Where one chunk of a checkpoint's entries is stored and how to check it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChunkRef {
    /// Offset of the payload, relative to the checkpoint's start.
    pub offset: u64,
    /// Payload bytes.
    pub stored_len: u32,
    /// [`Codec::Raw`] (the little-endian entries) or [`Codec::Zstd`].
    pub codec: Codec,
    /// xxh3 of the decoded entries' bytes.
    pub hash: u64,
    /// Bytes of the summary block that follows the payload (revision 5: flag
    /// [`CHUNK_HAS_SUMMARIES`], the length at bytes 14..16), 0 for none.
    pub summary_len: u16,
}

impl ChunkRef {
    /// The bytes a reader of the chunk needs, relative to the checkpoint's start: the payload
    /// and the summary block after it, which lie in a row (one fetch from a store).
    pub fn span(&self) -> (u64, u64) {
        (
            self.offset,
            u64::from(self.stored_len) + u64::from(self.summary_len),
        )
    }
}

/// A chunk's summary block (revision 5), bounds-checked, as [`Checkpoint::summaries`] returns
/// it: decode `payload` with `codec` and compare its xxh3 with `hash`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SummaryBlock<'a> {
    /// [`Codec::Raw`] or [`Codec::Zstd`].
    pub codec: Codec,
    /// xxh3 of the decoded summaries' bytes.
    pub hash: u64,
    /// The encoded summaries.
    pub payload: &'a [u8],
    /// Where the block starts in the file.
    pub offset: u64,
    /// Whether the summaries are wide (revision 6: block byte 9 is 1).
    pub wide: bool,
}

/// One chunk of a checkpoint to encode: its entries' payload (codec, bytes, xxh3 of the decoded
/// entries) and, in revision 5, its summaries' (the same three, of the decoded summaries).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EncodedChunk {
    /// How the entries are stored.
    pub codec: Codec,
    /// The stored entries.
    pub payload: Vec<u8>,
    /// xxh3 of the decoded entries.
    pub hash: u64,
    /// The summaries (codec, stored bytes, xxh3 of the decoded summaries), `None` for a chunk
    /// written as before revision 5.
    pub summaries: Option<(Codec, Vec<u8>, u64)>,
    /// Whether the summaries are wide (revision 6, a file with a u32 or u64 channel).
    pub wide_summaries: bool,
}

impl EncodedChunk {
    fn summary_block(&self) -> Vec<u8> {
        match &self.summaries {
            None => Vec::new(),
            Some((codec, payload, hash)) => {
                let mut b = vec![0u8; SUMMARY_BLOCK_HEADER_LEN];
                put(&mut b, 0, &hash.to_le_bytes());
                b[8] = *codec as u8;
                b[9] = u8::from(self.wide_summaries);
                b.extend_from_slice(payload);
                b
            }
        }
    }
}

/// Bytes per chunk reference in a checkpoint's directory.
pub const CHUNK_REF_LEN: usize = 32;

/// An index checkpoint: the whole pyramidal index of one version, in chunks of
/// [`CHUNK_ENTRIES`] entries, each stored raw or zstd-compressed (constant runs shrink to a few
/// bytes).
///
/// ```text
/// 0            magic "VIDX", u32 entries per chunk (512)
/// 8            u64 node count
/// 16           u64 xxh3 of bytes [0, 16)
/// 24           chunk count x ChunkRef { u64 offset from the checkpoint's start, u32 stored
///                                       length, u8 codec, 3 bytes zero, u64 xxh3 of the
///                                       decoded entries, u64 xxh3 of the ref's first 24 bytes }
/// 24 + 32 n    chunk payloads
/// ```
///
/// Every part carries its own checksum, so opening a file checks only the 24 fixed bytes (open
/// time does not grow with the volume); a chunk's reference and payload are checked when the
/// chunk is first used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Checkpoint<'a> {
    /// Index entries the checkpoint holds.
    pub n_nodes: u64,
    base: u64,
    bytes: &'a [u8],
}

impl<'a> Checkpoint<'a> {
    /// Chunks of [`CHUNK_ENTRIES`] entries for `n_nodes` entries.
    pub fn n_chunks(n_nodes: u64) -> u64 {
        n_nodes.div_ceil(CHUNK_ENTRIES)
    }

    /// Length of the fixed part and the directory.
    pub fn directory_len(n_nodes: u64) -> u64 {
        CHECKPOINT_FIXED_LEN as u64 + Self::n_chunks(n_nodes) * CHUNK_REF_LEN as u64
    }

    /// Encodes a checkpoint from already encoded chunks; each chunk's summary block, if it
    /// has one, follows its payload.
    ///
    /// # Panics
    /// Not one chunk per 512 entries, or a summary block longer than a u16 counts (a block
    /// of 512 raw summaries takes 6,160 bytes).
    pub fn encode(n_nodes: u64, chunks: &[EncodedChunk]) -> Vec<u8> {
        assert_eq!(chunks.len() as u64, Self::n_chunks(n_nodes));
        let blocks: Vec<Vec<u8>> = chunks.iter().map(EncodedChunk::summary_block).collect();
        let dir_len = Self::directory_len(n_nodes) as usize;
        let total = dir_len
            + chunks.iter().map(|c| c.payload.len()).sum::<usize>()
            + blocks.iter().map(Vec::len).sum::<usize>();
        let mut b = vec![0u8; dir_len];
        b.reserve(total - dir_len);
        put(&mut b, 0, &CHECKPOINT_MAGIC);
        put(&mut b, 4, &(CHUNK_ENTRIES as u32).to_le_bytes());
        put(&mut b, 8, &n_nodes.to_le_bytes());
        seal(&mut b, 16);
        let mut offset = dir_len as u64;
        for (i, (chunk, block)) in chunks.iter().zip(&blocks).enumerate() {
            let at = CHECKPOINT_FIXED_LEN + i * CHUNK_REF_LEN;
            let r = &mut b[at..at + CHUNK_REF_LEN];
            put(r, 0, &offset.to_le_bytes());
            put(r, 8, &(chunk.payload.len() as u32).to_le_bytes());
            r[12] = chunk.codec as u8;
            if !block.is_empty() {
                let len = u16::try_from(block.len()).expect("a summary block fits a u16");
                r[13] = CHUNK_HAS_SUMMARIES;
                put(r, 14, &len.to_le_bytes());
            }
            put(r, 16, &chunk.hash.to_le_bytes());
            seal(r, 24);
            offset += (chunk.payload.len() + block.len()) as u64;
        }
        for (chunk, block) in chunks.iter().zip(&blocks) {
            b.extend_from_slice(&chunk.payload);
            b.extend_from_slice(block);
        }
        b
    }

    /// Validates a checkpoint's 24 fixed bytes and that its directory lies inside `avail`
    /// (everything from the checkpoint's start to the end of the committed region). Constant
    /// time: the directory's entries are checked one by one by [`Checkpoint::chunk`].
    ///
    /// # Errors
    /// Bad magic, node count different from the layout's, truncation, checksum mismatch.
    pub fn decode(avail: &'a [u8], base: u64, expected_nodes: u64) -> Result<Self, FormatError> {
        let f = Fields::new("index checkpoint", avail, base);
        f.magic(0, CHECKPOINT_MAGIC)?;
        f.checksum(16)?;
        let per_chunk = f.u32(4)?;
        if per_chunk as u64 != CHUNK_ENTRIES {
            return Err(FormatError::invalid(
                "index checkpoint",
                format!("{per_chunk} entries per chunk, expected {CHUNK_ENTRIES}"),
            ));
        }
        let n_nodes = f.u64(8)?;
        if n_nodes != expected_nodes {
            return Err(FormatError::invalid(
                "index checkpoint",
                format!("{n_nodes} entries, the volume has {expected_nodes} bricks"),
            ));
        }
        let dir_len = Self::directory_len(n_nodes);
        if dir_len > avail.len() as u64 {
            return Err(FormatError::Truncated {
                what: "index checkpoint directory",
                offset: base,
                needed: dir_len,
                available: avail.len() as u64,
            });
        }
        Ok(Checkpoint {
            n_nodes,
            base,
            bytes: avail,
        })
    }

    /// The reference of chunk `chunk` (its checksum verified) and its payload (bounds checked).
    ///
    /// # Errors
    /// The chunk is out of range, its reference fails its checksum, has an unknown codec, or its
    /// payload lies outside the region.
    pub fn chunk(&self, chunk: u64) -> Result<(ChunkRef, &'a [u8]), FormatError> {
        if chunk >= Self::n_chunks(self.n_nodes) {
            return Err(FormatError::invalid(
                "index checkpoint",
                format!("no chunk {chunk}"),
            ));
        }
        let at = CHECKPOINT_FIXED_LEN + chunk as usize * CHUNK_REF_LEN;
        let whole = Fields::new("index checkpoint", self.bytes, self.base);
        let f = Fields::new(
            "index chunk reference",
            whole.slice(at, CHUNK_REF_LEN)?,
            self.base + at as u64,
        );
        f.checksum(24)?;
        let codec = match f.slice(12, 1)?[0] {
            0 => Codec::Raw,
            2 => Codec::Zstd,
            other => {
                return Err(FormatError::Unsupported {
                    what: "index chunk codec",
                    detail: other.to_string(),
                })
            }
        };
        // Bytes 13..16 were zero before revision 5, and readers before it ignore them.
        let summary_len = if f.slice(13, 1)?[0] & CHUNK_HAS_SUMMARIES != 0 {
            let len = f.u16(14)?;
            if (len as usize) <= SUMMARY_BLOCK_HEADER_LEN {
                return Err(FormatError::invalid(
                    "index chunk reference",
                    format!(
                        "at {}: a summary block of {len} bytes",
                        self.base + at as u64
                    ),
                ));
            }
            len
        } else {
            0
        };
        let r = ChunkRef {
            offset: f.u64(0)?,
            stored_len: f.u32(8)?,
            codec,
            hash: f.u64(16)?,
            summary_len,
        };
        let payload = usize::try_from(r.offset)
            .ok()
            .and_then(|o| self.bytes.get(o..o.checked_add(r.stored_len as usize)?))
            .ok_or(FormatError::Truncated {
                what: "index chunk",
                offset: self.base.saturating_add(r.offset),
                needed: r.stored_len as u64,
                available: (self.bytes.len() as u64).saturating_sub(r.offset),
            })?;
        Ok((r, payload))
    }

    /// The summary block after a chunk's payload (revision 5; `r` from
    /// [`Checkpoint::chunk`]), its header checked and its bounds checked; `None` when the chunk
    /// has none. Its content is checked by decoding it and comparing the hash.
    ///
    /// # Errors
    /// The block lies outside the region, or its header has an unknown codec or stray bits.
    pub fn summaries(&self, r: &ChunkRef) -> Result<Option<SummaryBlock<'a>>, FormatError> {
        if r.summary_len == 0 {
            return Ok(None);
        }
        let start = r.offset.saturating_add(u64::from(r.stored_len));
        let offset = self.base.saturating_add(start);
        let block = usize::try_from(start)
            .ok()
            .and_then(|o| self.bytes.get(o..o.checked_add(r.summary_len as usize)?))
            .ok_or(FormatError::Truncated {
                what: "index chunk summaries",
                offset,
                needed: u64::from(r.summary_len),
                available: (self.bytes.len() as u64).saturating_sub(start),
            })?;
        let f = Fields::new("index chunk summaries", block, offset);
        let codec = match f.slice(8, 1)?[0] {
            0 => Codec::Raw,
            2 => Codec::Zstd,
            other => {
                return Err(FormatError::Unsupported {
                    what: "index chunk summaries codec",
                    detail: format!("{other} at offset {offset}"),
                })
            }
        };
        let wide = f.slice(9, 1)?[0];
        if wide > 1 || f.slice(10, 6)?.iter().any(|&b| b != 0) {
            return Err(FormatError::invalid(
                "index chunk summaries",
                format!("at offset {offset}: reserved bytes are not zero"),
            ));
        }
        Ok(Some(SummaryBlock {
            codec,
            hash: f.u64(0)?,
            payload: f.slice(
                SUMMARY_BLOCK_HEADER_LEN,
                block.len() - SUMMARY_BLOCK_HEADER_LEN,
            )?,
            offset,
            wide: wide == 1,
        }))
    }

    /// Entries in chunk `chunk` (512, fewer in the last).
    pub fn chunk_entries(&self, chunk: u64) -> u64 {
        CHUNK_ENTRIES.min(self.n_nodes - chunk * CHUNK_ENTRIES)
    }

    /// Bytes from the checkpoint's start to the end of its last payload (reads every chunk
    /// reference: for tools, not for opening).
    ///
    /// # Errors
    /// A chunk reference is invalid.
    pub fn total_len(&self) -> Result<u64, FormatError> {
        let mut end = Self::directory_len(self.n_nodes);
        for c in 0..Self::n_chunks(self.n_nodes) {
            let (r, _) = self.chunk(c)?;
            let (at, len) = r.span();
            end = end.max(at + len);
        }
        Ok(end)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> VolumeLayout {
        VolumeLayout::new([200, 160, 160], 16, VoxelType::U16).unwrap()
    }

    #[test]
    fn header_round_trips_and_starts_like_vod1() {
        let h = FileHeader::new(layout(), [1.0, 0.5, 2.0]);
        let b = h.encode();
        // Golden bytes: '.VOD', version 2, as VOD 1 starts with '.VOD', version 1.
        assert_eq!(&b[..8], &[b'.', b'V', b'O', b'D', 2, 0, 0, 0]);
        // dims 200 = 0xc8, 160 = 0xa0 little endian.
        assert_eq!(&b[16..28], &[0xc8, 0, 0, 0, 0xa0, 0, 0, 0, 0xa0, 0, 0, 0]);
        assert_eq!(FileHeader::decode(&b).unwrap(), h);
    }

    #[test]
    fn header_flip_is_detected() {
        let b = FileHeader::new(layout(), [1.0; 3]).encode();
        for i in 0..HEADER_LEN {
            let mut c = b;
            c[i] ^= 0x10;
            assert!(
                FileHeader::decode(&c).is_err(),
                "flip at byte {i} not detected"
            );
        }
    }

    #[test]
    fn slot_round_trip_and_rejects_bad_offsets() {
        let s = HeaderSlot {
            seq: 7,
            commit: DATA_START + 100,
            committed_len: DATA_START + 1000,
            version: 3,
            appended: None,
        };
        assert_eq!(HeaderSlot::decode(&s.encode(), 4096).unwrap(), s);
        let bad = HeaderSlot {
            commit: DATA_START + 990,
            ..s
        };
        assert!(HeaderSlot::decode(&bad.encode(), 4096).is_err());
        assert!(HeaderSlot::decode(&[0u8; SLOT_LEN], 4096).is_err());
    }

    #[test]
    fn slot_with_appended_check_round_trips_and_seals_its_extension() {
        let s = HeaderSlot {
            seq: 9,
            commit: DATA_START + 500,
            committed_len: DATA_START + 1000,
            version: 4,
            appended: Some(AppendedCheck {
                from: DATA_START + 200,
                checksum: 0xfeed_f00d_dead_beef,
            }),
        };
        let bytes = s.encode();
        assert_eq!(HeaderSlot::decode(&bytes, 4096).unwrap(), s);
        // The first 48 bytes are what a reader before revision 2 reads: still a valid slot
        // naming the same commit (it only skips the check).
        assert_eq!(
            xxh3_64(&bytes[..40]).to_le_bytes(),
            bytes[40..48],
            "the base checksum covers bytes [0, 40) as before"
        );
        for i in 48..SLOT_LEN {
            let mut flipped = bytes;
            flipped[i] ^= 0x10;
            assert!(
                HeaderSlot::decode(&flipped, 4096).is_err(),
                "flip at byte {i} of the extension not detected"
            );
        }
        // The appended bytes must hold the head commit.
        for from in [DATA_START - 1, DATA_START + 501] {
            let bad = HeaderSlot {
                appended: Some(AppendedCheck { from, checksum: 1 }),
                ..s
            };
            assert!(
                HeaderSlot::decode(&bad.encode(), 4096).is_err(),
                "from {from}"
            );
        }
        // Unknown flags are refused.
        let mut unknown = HeaderSlot {
            appended: None,
            ..s
        }
        .encode();
        unknown[4] = 2;
        seal(&mut unknown, 40);
        assert!(HeaderSlot::decode(&unknown, 4096).is_err());
    }

    #[test]
    fn brick_header_round_trip_and_validation() {
        let l = layout();
        let h = BrickHeader {
            hash: 0x0123_4567_89ab_cdef,
            stored_len: 100,
            codec: Codec::Lz4,
            min: 0,
            max: 65535,
            checked: true,
            wide: false,
        };
        assert_eq!(BrickHeader::decode(&h.encode(), 0, &l).unwrap(), h);
        assert_eq!(h.record_len(), 24 + 100 + 4);
        // A record written before payload checksums: byte 13 zero, no checksum after the payload.
        let legacy = BrickHeader {
            checked: false,
            ..h
        };
        let bytes = legacy.encode();
        assert_eq!((h.encode()[13], bytes[13]), (1, 0));
        assert_eq!(BrickHeader::decode(&bytes, 0, &l).unwrap(), legacy);
        assert_eq!(legacy.record_len(), 24 + 100);
        // Flags this reader does not know are refused, not ignored (the header checksum is
        // made right, so only the flag is wrong).
        let mut unknown = h.encode();
        unknown[13] = 0x03;
        let check = xxh3_64(&unknown[..20]) as u32;
        unknown[20..24].copy_from_slice(&check.to_le_bytes());
        assert!(BrickHeader::decode(&unknown, 0, &l).is_err());
        let raw_wrong_len = BrickHeader {
            codec: Codec::Raw,
            ..h
        };
        assert!(BrickHeader::decode(&raw_wrong_len.encode(), 0, &l).is_err());
        let inverted = BrickHeader {
            min: 9,
            max: 3,
            ..h
        };
        assert!(BrickHeader::decode(&inverted.encode(), 0, &l).is_err());
        // A wide record where the stream is u16: refused by its flag, not misread.
        let wide = BrickHeader { wide: true, ..h };
        assert!(BrickHeader::decode(&wide.encode(), 0, &l).is_err());
    }

    #[test]
    fn a_wide_brick_header_holds_a_u64_range_in_40_bytes() {
        let l = layout().with_voxel_type(VoxelType::U64);
        let h = BrickHeader {
            hash: 7,
            stored_len: 100,
            codec: Codec::Zstd,
            min: 1 << 40,
            max: u64::MAX,
            checked: true,
            wide: true,
        };
        let b = h.encode();
        // Written by hand from docs/vod2.md: flags 1 | 2 at 13, min at 16, max at 24, the
        // checksum of [0, 32) at 32.
        assert_eq!(b.len(), 40);
        assert_eq!(b[13], 3);
        assert_eq!(b[16..24], (1u64 << 40).to_le_bytes());
        assert_eq!(b[24..32], [0xff; 8]);
        assert_eq!(b[32..36], (xxh3_64(&b[..32]) as u32).to_le_bytes());
        assert_eq!(BrickHeader::decode(&b, 0, &l).unwrap(), h);
        assert_eq!(h.record_len(), 40 + 100 + 4);
        // A u32 stream refuses a range past u32, and a narrow record where it expects wide.
        let l32 = layout().with_voxel_type(VoxelType::U32);
        assert!(BrickHeader::decode(&b, 0, &l32).is_err());
        let narrow = BrickHeader {
            wide: false,
            min: 1,
            max: 2,
            ..h
        };
        assert!(BrickHeader::decode(&narrow.encode(), 0, &l32).is_err());
    }

    #[test]
    fn payload_check_is_the_low_half_of_xxh3() {
        // xxHash's published test vector: XXH3_64bits of no bytes is 0x2D06800538D394C2.
        assert_eq!(payload_check(&[]), 0x38D3_94C2);
        assert_ne!(payload_check(&[1, 2, 3]), payload_check(&[1, 2, 4]));
    }

    #[test]
    fn node_entries() {
        let t = VoxelType::U8;
        assert_eq!(
            NodeEntry::decode(NodeEntry::Constant(255).encode(), t, 1 << 20),
            Ok(NodeEntry::Constant(255))
        );
        assert!(NodeEntry::decode(NodeEntry::Constant(256).encode(), t, 1 << 20).is_err());
        assert_eq!(
            NodeEntry::decode(DATA_START, t, DATA_START + 24),
            Ok(NodeEntry::Stored(DATA_START))
        );
        assert!(NodeEntry::decode(DATA_START, t, DATA_START + 23).is_err());
        assert!(NodeEntry::decode(5, t, 1 << 20).is_err());
    }

    #[test]
    fn commit_round_trip() {
        let changes = vec![
            (3, NodeEntry::Constant(9)),
            (5, NodeEntry::Stored(DATA_START)),
        ];
        let h = CommitHeader {
            version: 2,
            parent: DATA_START + 8,
            timestamp_ms: 1234,
            checkpoint: 0,
            n_changes: 2,
            note_len: 0,
            summaries: false,
            wide_summaries: false,
        };
        let base = DATA_START + 4096;
        let mut bytes = h.encode(&changes, &[], None);
        bytes.extend_from_slice(&[0xAA; 10]); // trailing bytes of the region are ignored
        let (d, rec) = CommitHeader::decode(&bytes, base).unwrap();
        assert_eq!(d, h);
        let got: Vec<_> = CommitHeader::changes(rec).collect();
        assert_eq!(
            got,
            vec![(3, NodeEntry::Constant(9).encode()), (5, DATA_START)]
        );
        // A huge change count cannot make the decoder allocate or read past the region.
        let mut hostile = h.encode(&changes, &[], None);
        hostile[40..48].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(CommitHeader::decode(&hostile, base).is_err());
    }

    #[test]
    fn a_note_follows_the_record_where_older_readers_do_not_look() {
        let changes = vec![(3, NodeEntry::Constant(9))];
        let note = br#"{"author":"alice"}"#;
        let h = CommitHeader {
            version: 2,
            parent: DATA_START + 8,
            timestamp_ms: 1234,
            checkpoint: 0,
            n_changes: 1,
            note_len: note.len() as u32,
            summaries: false,
            wide_summaries: false,
        };
        let base = DATA_START + 4096;
        let bytes = h.encode(&changes, note, None);
        let record_len = CommitHeader::record_len(1) as usize;
        assert_eq!(bytes.len(), record_len + 4 + note.len() + 8);
        assert_eq!(h.total_len(), bytes.len() as u64);
        let (d, rec) = CommitHeader::decode(&bytes, base).unwrap();
        assert_eq!(d, h);
        assert_eq!(rec.len(), record_len);
        assert_eq!(d.note(&bytes), note);
        // What a reader before revision 3 checks: the record's own checksum over its first
        // bytes, which the note does not touch.
        let stored = u64::from_le_bytes(bytes[record_len - 8..record_len].try_into().unwrap());
        assert_eq!(stored, xxh3_64(&bytes[..record_len - 8]));
        // A changed note byte, a cut note, an absurd length: each refused.
        let mut flipped = bytes.clone();
        flipped[record_len + 6] ^= 1;
        assert!(CommitHeader::decode(&flipped, base).is_err());
        assert!(CommitHeader::decode(&bytes[..bytes.len() - 1], base).is_err());
        let mut absurd = bytes.clone();
        absurd[record_len..record_len + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(CommitHeader::decode(&absurd, base).is_err());
    }

    #[test]
    fn checkpoint_round_trip_and_bounds() {
        // 1300 entries: chunks of 512, 512, 276.
        let chunk = |codec, payload, hash| EncodedChunk {
            codec,
            payload,
            hash,
            summaries: None,
            wide_summaries: false,
        };
        let chunks = vec![
            chunk(Codec::Raw, vec![1u8; 512 * 8], 11),
            chunk(Codec::Zstd, vec![2u8; 40], 22),
            chunk(Codec::Raw, vec![3u8; 276 * 8], 33),
        ];
        let b = Checkpoint::encode(1300, &chunks);
        let cp = Checkpoint::decode(&b, DATA_START, 1300).unwrap();
        assert_eq!(Checkpoint::n_chunks(1300), 3);
        assert_eq!(cp.chunk_entries(2), 276);
        assert_eq!(cp.total_len().unwrap() as usize, b.len());
        let (r, p) = cp.chunk(1).unwrap();
        assert_eq!((r.codec, r.hash, p), (Codec::Zstd, 22, &[2u8; 40][..]));
        assert_eq!(cp.summaries(&r).unwrap(), None);
        assert!(cp.chunk(3).is_err());
        assert!(Checkpoint::decode(&b, DATA_START, 1299).is_err());
        // A directory flip fails the checksum; a truncated region fails the chunk bounds.
        let mut flipped = b.clone();
        flipped[8] ^= 1; // node count: fixed-part checksum
        assert!(Checkpoint::decode(&flipped, DATA_START, 1300).is_err());
        let mut flipped = b.clone();
        flipped[24 + 32 + 8] ^= 1; // chunk 1's stored length: its reference checksum
        let cp = Checkpoint::decode(&flipped, DATA_START, 1300).unwrap();
        assert!(cp.chunk(0).is_ok());
        assert!(cp.chunk(1).is_err());
        let short = &b[..b.len() - 1];
        let cp = Checkpoint::decode(short, DATA_START, 1300).unwrap();
        assert!(cp.chunk(2).is_err());
    }

    #[test]
    fn summaries_follow_the_note_where_older_readers_do_not_look() {
        let changes = vec![
            (3, NodeEntry::Constant(9)),
            (5, NodeEntry::Stored(DATA_START)),
        ];
        let summaries = [
            BrickSummary::default(),
            BrickSummary {
                hash: 0x0102_0304_0506_0708,
                min: 3,
                max: 200,
            },
        ];
        let note = br#"{"author":"alice"}"#;
        let h = CommitHeader {
            version: 2,
            parent: DATA_START + 8,
            timestamp_ms: 1234,
            checkpoint: 0,
            n_changes: 2,
            note_len: note.len() as u32,
            summaries: true,
            wide_summaries: false,
        };
        let base = DATA_START + 4096;
        let bytes = h.encode(&changes, note, Some(&summaries));
        let record_len = CommitHeader::record_len(2) as usize;
        let with_note = record_len + 12 + note.len();
        // Golden layout: 12 bytes a summary, then a checksum of everything before it.
        assert_eq!(bytes.len(), with_note + 2 * 12 + 8);
        assert_eq!(h.total_len(), bytes.len() as u64);
        assert_eq!(&bytes[4..8], &[3, 0, 0, 0]); // note and summaries flags
        assert_eq!(
            &bytes[with_note + 12..with_note + 24],
            &[8, 7, 6, 5, 4, 3, 2, 1, 3, 0, 200, 0]
        );
        let stored = u64::from_le_bytes(bytes[bytes.len() - 8..].try_into().unwrap());
        assert_eq!(stored, xxh3_64(&bytes[..bytes.len() - 8]));
        // What older readers check is unchanged: the record's and the note's checksums.
        let stored = u64::from_le_bytes(bytes[record_len - 8..record_len].try_into().unwrap());
        assert_eq!(stored, xxh3_64(&bytes[..record_len - 8]));
        let (d, rec) = CommitHeader::decode(&bytes, base).unwrap();
        assert_eq!(d, h);
        assert_eq!(d.note(&bytes), note);
        assert_eq!(CommitHeader::changes(rec).count(), 2);
        assert_eq!(d.summaries_in(&bytes).unwrap(), summaries.to_vec());
        // Any flipped summary byte, or a cut section, is refused.
        for at in with_note..bytes.len() {
            let mut flipped = bytes.clone();
            flipped[at] ^= 0x40;
            assert!(CommitHeader::decode(&flipped, base).is_err(), "byte {at}");
        }
        assert!(CommitHeader::decode(&bytes[..bytes.len() - 1], base).is_err());
        // Without a note the section follows the record directly.
        let h = CommitHeader { note_len: 0, ..h };
        let bytes = h.encode(&changes, &[], Some(&summaries));
        assert_eq!(bytes.len(), record_len + 2 * 12 + 8);
        let (d, _) = CommitHeader::decode(&bytes, base).unwrap();
        assert_eq!(d.summaries_in(&bytes).unwrap(), summaries.to_vec());
    }

    #[test]
    fn a_chunk_summary_block_follows_its_payload() {
        let chunks = vec![
            EncodedChunk {
                codec: Codec::Raw,
                payload: vec![1u8; 512 * 8],
                hash: 11,
                summaries: Some((Codec::Raw, vec![7u8; 512 * 12], 44)),
                wide_summaries: false,
            },
            EncodedChunk {
                codec: Codec::Zstd,
                payload: vec![2u8; 40],
                hash: 22,
                summaries: None,
                wide_summaries: true,
            },
        ];
        let b = Checkpoint::encode(600, &chunks);
        let cp = Checkpoint::decode(&b, DATA_START, 600).unwrap();
        assert_eq!(cp.total_len().unwrap() as usize, b.len());
        let (r, p) = cp.chunk(0).unwrap();
        assert_eq!((r.stored_len, p.len()), (4096, 4096));
        // Golden reference bytes 12..16: codec, flag, u16 block length (16 + 6144 = 6160).
        let dir = CHECKPOINT_FIXED_LEN;
        assert_eq!(&b[dir + 12..dir + 16], &[0, 1, 0x10, 0x18]);
        let block = cp.summaries(&r).unwrap().unwrap();
        assert_eq!(
            (block.codec, block.hash, block.wide),
            (Codec::Raw, 44, false)
        );
        assert_eq!(block.payload, &[7u8; 512 * 12][..]);
        assert_eq!(block.offset, DATA_START + r.offset + 4096);
        // The block lies right after the payload: one span covers both.
        assert_eq!(r.span(), (r.offset, 4096 + 6160));
        let (r1, p1) = cp.chunk(1).unwrap();
        assert_eq!(p1, &[2u8; 40][..]);
        assert_eq!(r1.offset, r.offset + 4096 + 6160);
        assert_eq!(cp.summaries(&r1).unwrap(), None);
        // A reader before revision 5 reads what it always read: offset, length, codec, hash.
        assert_eq!(
            u64::from_le_bytes(b[dir..dir + 8].try_into().unwrap()),
            r.offset
        );
        // A bad block header codec or stray bits are refused; a cut block too.
        let at = (r.offset + 4096) as usize;
        let mut bad = b.clone();
        bad[at + 8] = 9;
        let cp_bad = Checkpoint::decode(&bad, DATA_START, 600).unwrap();
        assert!(cp_bad.summaries(&r).is_err());
        let mut bad = b.clone();
        bad[at + 12] = 1;
        let cp_bad = Checkpoint::decode(&bad, DATA_START, 600).unwrap();
        assert!(cp_bad.summaries(&r).is_err());
        let short = Checkpoint::decode(&b[..at + 100], DATA_START, 600).unwrap();
        assert!(short.summaries(&r).is_err());
    }

    #[test]
    fn wide_summaries_are_flagged_in_commits_and_summary_blocks() {
        let changes = vec![
            (3, NodeEntry::Stored(DATA_START)),
            (4, NodeEntry::Constant(9)),
        ];
        let summaries = [
            BrickSummary {
                hash: 5,
                min: 1 << 33,
                max: u64::MAX,
            },
            BrickSummary::default(),
        ];
        let h = CommitHeader {
            version: 2,
            parent: DATA_START + 8,
            timestamp_ms: 1,
            checkpoint: 0,
            n_changes: 2,
            note_len: 0,
            summaries: true,
            wide_summaries: true,
        };
        let base = DATA_START + 4096;
        let bytes = h.encode(&changes, &[], Some(&summaries));
        // Flags 2 | 4; the record, then 2 x 24 bytes and the section's checksum.
        assert_eq!(bytes[4..8], 6u32.to_le_bytes());
        let record_len = CommitHeader::record_len(2) as usize;
        assert_eq!(bytes.len(), record_len + 2 * 24 + 8);
        assert_eq!(bytes[record_len + 16..record_len + 24], [0xff; 8]);
        let (d, _) = CommitHeader::decode(&bytes, base).unwrap();
        assert!(d.wide_summaries);
        assert_eq!(d.summaries_in(&bytes).unwrap(), summaries.to_vec());
        // A summary block says its width in byte 9; other values there are refused.
        let chunk = EncodedChunk {
            codec: Codec::Raw,
            payload: vec![1u8; 8],
            hash: 1,
            summaries: Some((Codec::Raw, vec![0u8; 24], 2)),
            wide_summaries: true,
        };
        let b = Checkpoint::encode(1, std::slice::from_ref(&chunk));
        let cp = Checkpoint::decode(&b, DATA_START, 1).unwrap();
        let (r, _) = cp.chunk(0).unwrap();
        assert!(cp.summaries(&r).unwrap().unwrap().wide);
        let mut bad = b.clone();
        bad[(r.offset + 8 + 9) as usize] = 2;
        let cp_bad = Checkpoint::decode(&bad, DATA_START, 1).unwrap();
        assert!(cp_bad.summaries(&r).is_err());
    }

    #[test]
    fn summary_ranges_are_validated() {
        let s = BrickSummary {
            hash: 1,
            min: 4,
            max: 3,
        };
        assert!(s.validate(VoxelType::U16, "x", 0).is_err());
        let s = BrickSummary {
            min: 0,
            max: 256,
            ..s
        };
        assert!(s.validate(VoxelType::U8, "x", 0).is_err());
        assert!(s.validate(VoxelType::U16, "x", 0).is_ok());
        let mut b = Vec::new();
        s.encode_into(&mut b, false);
        assert_eq!(b, [1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1]);
        assert_eq!(BrickSummary::decode(&b, false), s);
        let big = BrickSummary {
            hash: 2,
            min: 70_000,
            max: u64::MAX,
        };
        assert!(big.validate(VoxelType::U32, "x", 0).is_err());
        assert!(big.validate(VoxelType::U64, "x", 0).is_ok());
        let all = BrickSummary::encode_all(&[s, big], true);
        assert_eq!(all.len(), 48);
        assert_eq!(all[32..40], 70_000u64.to_le_bytes());
        assert_eq!(BrickSummary::decode_all(&all, true), [s, big]);
    }
}
