//! Zarr's compressing codecs, decoded only as far as the chunk can hold.
//!
//! zarrs decodes a zstd frame into a buffer of the size the frame's header declares, and gzip
//! and zlib streams to their end: a chunk of a few hundred kilobytes can declare or hold
//! gigabytes, and the process would take them (or abort when the allocation fails). [`install`]
//! sends the names of those codecs, and of blosc, in Zarr v2 and v3 metadata (inside a sharding
//! codec too) to [`Bounded`] instead. Every place a codec decodes, zarrs tells it the size of
//! what it decodes to (the chunk's bytes, or a bound on them when another codec follows), so
//! [`Bounded`] reads zstd, gzip and zlib through streaming decoders that stop one byte past that
//! size, and refuses a blosc buffer whose header declares more before zarrs decodes it.
//! Encoding is zarrs's own.

use std::borrow::Cow;
use std::io::Read;
use std::sync::{Arc, Once};
use zarrs::array::codec::{
    BytesToBytesCodecTraits, Codec, CodecError, CodecMetadataOptions, CodecOptions, CodecPlugin,
    CodecTraits, PartialDecoderCapability, PartialEncoderCapability,
};
use zarrs::array::{BytesRepresentation, RawBytes, RecommendedConcurrency};
use zarrs::metadata::v3::MetadataV3;
use zarrs::metadata::Configuration;
use zarrs::plugin::PluginCreateError;
use zarrs::registry::ExtensionAliasesCodecV3;

/// The codecs decoded here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Zstd,
    Gzip,
    Zlib,
    Blosc,
}

impl Kind {
    const ALL: [Kind; 4] = [Kind::Zstd, Kind::Gzip, Kind::Zlib, Kind::Blosc];

    /// zarrs's identifier of the codec (its Zarr v3 name).
    fn zarrs(self) -> &'static str {
        match self {
            Kind::Zstd => zarrs::registry::codec::ZSTD,
            Kind::Gzip => zarrs::registry::codec::GZIP,
            Kind::Zlib => zarrs::registry::codec::ZLIB,
            Kind::Blosc => zarrs::registry::codec::BLOSC,
        }
    }

    /// The identifier the codec's names lead to once [`install`]ed.
    fn identifier(self) -> &'static str {
        match self {
            Kind::Zstd => "isovox.bounded.zstd",
            Kind::Gzip => "isovox.bounded.gzip",
            Kind::Zlib => "isovox.bounded.zlib",
            Kind::Blosc => "isovox.bounded.blosc",
        }
    }
}

inventory::submit! {
    CodecPlugin::new("isovox.bounded.zstd", |n| n == Kind::Zstd.identifier(), |m| create(Kind::Zstd, m))
}
inventory::submit! {
    CodecPlugin::new("isovox.bounded.gzip", |n| n == Kind::Gzip.identifier(), |m| create(Kind::Gzip, m))
}
inventory::submit! {
    CodecPlugin::new("isovox.bounded.zlib", |n| n == Kind::Zlib.identifier(), |m| create(Kind::Zlib, m))
}
inventory::submit! {
    CodecPlugin::new("isovox.bounded.blosc", |n| n == Kind::Blosc.identifier(), |m| create(Kind::Blosc, m))
}

/// Makes every Zarr array opened afterwards in this process decode zstd, gzip, zlib and blosc
/// through [`Bounded`].
pub fn install() {
    static INSTALLED: Once = Once::new();
    INSTALLED.call_once(|| {
        let mut config = zarrs::config::global_config_mut();
        let aliases = config.codec_aliases_v3_mut();
        for kind in Kind::ALL {
            // Every name that led to zarrs's codec (its own, and aliases such as numcodecs.zlib).
            let names: Vec<Cow<'static, str>> = aliases
                .aliases_str
                .iter()
                .filter(|(_, id)| **id == kind.zarrs())
                .map(|(name, _)| name.clone())
                .collect();
            for name in names {
                aliases.aliases_str.insert(name, kind.identifier());
            }
            aliases
                .aliases_str
                .insert(Cow::Borrowed(kind.zarrs()), kind.identifier());
        }
    });
}

/// zarrs's codec for `metadata`, wrapped.
fn create(kind: Kind, metadata: &MetadataV3) -> Result<Codec, PluginCreateError> {
    // The default aliases, not the global ones: these lead to zarrs's own codec.
    match Codec::from_metadata(metadata, &ExtensionAliasesCodecV3::default())? {
        Codec::BytesToBytes(inner) => Ok(Codec::BytesToBytes(Arc::new(Bounded { kind, inner }))),
        _ => Err(PluginCreateError::Other(format!(
            "{} is not a bytes-to-bytes codec",
            kind.zarrs()
        ))),
    }
}

/// A compressing codec of zarrs whose decoding stops at the size it decodes to.
#[derive(Debug)]
pub struct Bounded {
    kind: Kind,
    inner: Arc<dyn BytesToBytesCodecTraits>,
}

/// The size of a blosc header; bytes 4..8 are the decoded size (little endian).
const BLOSC_HEADER: usize = 16;

/// Reads `r` to its end into at most `bound` bytes.
///
/// # Errors
/// More than `bound` bytes, or what the decoder fails with.
fn read_within(r: impl Read, bound: u64, what: &str) -> Result<Vec<u8>, CodecError> {
    // The capacity is the bound (the chunk's size, not what the data claims); reading stops one
    // byte past it, so a bomb costs the chunk's size, not its own.
    let mut out = Vec::with_capacity(usize::try_from(bound).unwrap_or(0).min(64 << 20));
    r.take(bound.saturating_add(1))
        .read_to_end(&mut out)
        .map_err(|e| CodecError::Other(format!("{what} data does not decode: {e}")))?;
    if out.len() as u64 > bound {
        return Err(CodecError::Other(format!(
            "{what} data decodes to more than the {bound} bytes a chunk holds"
        )));
    }
    Ok(out)
}

/// The decoded size of a blosc buffer, as its header declares it.
fn blosc_declared(encoded: &[u8]) -> Option<u64> {
    let b = encoded.get(4..8)?;
    (encoded.len() >= BLOSC_HEADER).then(|| u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])))
}

impl Bounded {
    /// Decodes `encoded` into at most `bound` bytes.
    fn decode_within(&self, encoded: &[u8], bound: u64) -> Result<Vec<u8>, CodecError> {
        match self.kind {
            Kind::Zstd => {
                let decoder = zstd::stream::read::Decoder::with_buffer(encoded)
                    .map_err(|e| CodecError::Other(format!("zstd data does not decode: {e}")))?;
                read_within(decoder, bound, "zstd")
            }
            Kind::Gzip => read_within(flate2::read::GzDecoder::new(encoded), bound, "gzip"),
            Kind::Zlib => read_within(flate2::read::ZlibDecoder::new(encoded), bound, "zlib"),
            Kind::Blosc => {
                let declared = blosc_declared(encoded).ok_or_else(|| {
                    CodecError::Other(format!(
                        "blosc data of {} bytes is shorter than its header",
                        encoded.len()
                    ))
                })?;
                if declared > bound {
                    return Err(CodecError::Other(format!(
                        "blosc data declares {declared} bytes, more than the {bound} bytes a chunk holds"
                    )));
                }
                // zarrs decodes into exactly the declared size, now known to be within bound.
                let decoded = self.inner.decode(
                    Cow::Borrowed(encoded),
                    &BytesRepresentation::BoundedSize(bound),
                    &CodecOptions::default(),
                )?;
                Ok(decoded.into_owned())
            }
        }
    }
}

impl CodecTraits for Bounded {
    fn identifier(&self) -> &str {
        // zarrs's, so that metadata written from this codec names the codec as it was named.
        self.inner.identifier()
    }

    fn configuration_opt(
        &self,
        name: &str,
        options: &CodecMetadataOptions,
    ) -> Option<Configuration> {
        self.inner.configuration_opt(name, options)
    }

    fn partial_decoder_capability(&self) -> PartialDecoderCapability {
        self.inner.partial_decoder_capability()
    }

    fn partial_encoder_capability(&self) -> PartialEncoderCapability {
        self.inner.partial_encoder_capability()
    }
}

impl BytesToBytesCodecTraits for Bounded {
    fn into_dyn(self: Arc<Self>) -> Arc<dyn BytesToBytesCodecTraits> {
        self as Arc<dyn BytesToBytesCodecTraits>
    }

    fn recommended_concurrency(
        &self,
        decoded_representation: &BytesRepresentation,
    ) -> Result<RecommendedConcurrency, CodecError> {
        self.inner.recommended_concurrency(decoded_representation)
    }

    fn encoded_representation(
        &self,
        decoded_representation: &BytesRepresentation,
    ) -> BytesRepresentation {
        self.inner.encoded_representation(decoded_representation)
    }

    fn encode<'a>(
        &self,
        decoded_value: RawBytes<'a>,
        options: &CodecOptions,
    ) -> Result<RawBytes<'a>, CodecError> {
        self.inner.encode(decoded_value, options)
    }

    fn decode<'a>(
        &self,
        encoded_value: RawBytes<'a>,
        decoded_representation: &BytesRepresentation,
        _options: &CodecOptions,
    ) -> Result<RawBytes<'a>, CodecError> {
        let bound = match *decoded_representation {
            BytesRepresentation::FixedSize(n) | BytesRepresentation::BoundedSize(n) => n,
            BytesRepresentation::UnboundedSize => {
                return Err(CodecError::Other(format!(
                    "{} data whose decoded size has no bound (a variable-length type?) is not read",
                    self.kind.zarrs()
                )))
            }
        };
        let decoded = self.decode_within(&encoded_value, bound)?;
        if let BytesRepresentation::FixedSize(n) = *decoded_representation {
            if decoded.len() as u64 != n {
                return Err(CodecError::Other(format!(
                    "{} data decodes to {} bytes; the chunk holds {n}",
                    self.kind.zarrs(),
                    decoded.len()
                )));
            }
        }
        Ok(Cow::Owned(decoded))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The codec zarrs makes for `kind`'s standard name once [`install`]ed.
    fn bounded(kind: Kind) -> Arc<dyn BytesToBytesCodecTraits> {
        install();
        let name = kind.zarrs();
        let configuration = match kind {
            Kind::Zstd => r#"{"level": 1, "checksum": false}"#,
            Kind::Gzip | Kind::Zlib => r#"{"level": 1}"#,
            Kind::Blosc => {
                r#"{"cname": "lz4", "clevel": 5, "shuffle": "noshuffle", "typesize": 1, "blocksize": 0}"#
            }
        };
        let metadata: MetadataV3 = serde_json::from_str(&format!(
            r#"{{"name": "{name}", "configuration": {configuration}}}"#
        ))
        .unwrap();
        let aliases = zarrs::config::global_config().codec_aliases_v3().clone();
        assert_eq!(aliases.identifier(name), kind.identifier());
        match Codec::from_metadata(&metadata, &aliases).unwrap() {
            Codec::BytesToBytes(codec) => codec,
            other => panic!("{name}: {other:?}"),
        }
    }

    #[test]
    fn every_codec_round_trips_within_its_size_and_refuses_more() {
        let data: Vec<u8> = (0..4096u32).map(|i| (i * 7 % 251) as u8).collect();
        let fixed = BytesRepresentation::FixedSize(data.len() as u64);
        let options = CodecOptions::default();
        for kind in Kind::ALL {
            let codec = bounded(kind);
            let encoded = codec.encode(Cow::Borrowed(&data), &options).unwrap();
            let decoded = codec.decode(encoded.clone(), &fixed, &options).unwrap();
            assert_eq!(decoded.as_ref(), &data[..], "{kind:?}");
            // The same data is more than a chunk of half its size holds.
            let half = BytesRepresentation::FixedSize(data.len() as u64 / 2);
            let err = codec
                .decode(encoded, &half, &options)
                .unwrap_err()
                .to_string();
            assert!(err.contains("more than the 2048 bytes"), "{kind:?}: {err}");
        }
    }

    #[test]
    fn a_zstd_frame_declaring_gigabytes_is_read_no_further_than_the_chunk() {
        // A frame that declares (and holds) 64 MiB of zeros, for a chunk of 4 KiB.
        let mut encoder = zstd::stream::write::Encoder::new(Vec::new(), 1).unwrap();
        encoder.set_pledged_src_size(Some(64 << 20)).unwrap();
        encoder.include_contentsize(true).unwrap();
        let zeros = vec![0u8; 1 << 20];
        for _ in 0..64 {
            std::io::Write::write_all(&mut encoder, &zeros).unwrap();
        }
        let frame = encoder.finish().unwrap();
        let codec = bounded(Kind::Zstd);
        let err = codec
            .decode(
                Cow::Owned(frame),
                &BytesRepresentation::FixedSize(4096),
                &CodecOptions::default(),
            )
            .unwrap_err()
            .to_string();
        assert!(err.contains("more than the 4096 bytes"), "{err}");
    }

    #[test]
    fn a_blosc_header_declaring_more_than_the_chunk_is_refused_before_decoding() {
        let codec = bounded(Kind::Blosc);
        let data = vec![5u8; 8192];
        let mut encoded = codec
            .encode(Cow::Borrowed(&data), &CodecOptions::default())
            .unwrap()
            .into_owned();
        encoded[4..8].copy_from_slice(&(1u32 << 31).to_le_bytes());
        let err = codec
            .decode(
                Cow::Owned(encoded),
                &BytesRepresentation::FixedSize(8192),
                &CodecOptions::default(),
            )
            .unwrap_err()
            .to_string();
        assert!(err.contains("declares 2147483648 bytes"), "{err}");
        assert!(codec
            .decode(
                Cow::Owned(vec![2, 1]),
                &BytesRepresentation::FixedSize(8192),
                &CodecOptions::default()
            )
            .is_err());
    }
}
