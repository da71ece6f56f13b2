//! Numbers in URLs: one spelling each.
//!
//! A number in a request's path or query (a level, a brick or chunk coordinate, a version) is
//! read only in its canonical decimal spelling: ASCII digits, no sign, no leading zero (but `0`
//! itself), no percent-escapes. `str::parse` also takes `+1` and `01`, and the router decodes
//! `%31` to `1` before a handler sees it, so every such spelling used to name the same document
//! and HTTP caches kept a copy of one chunk under each. Now another spelling of a number names
//! nothing (404); text that is no number at all stays what each route made it (a malformed
//! path, 400, or a document the view does not have, 404).

use std::str::FromStr;

/// Why a segment was not read as a number.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NotCanonical {
    /// A number, spelled another way than the one the server answers (a sign, a leading zero,
    /// a percent-escaped digit): it names nothing.
    OtherSpelling,
    /// Not a number of the type asked for (no digits, other characters, out of range).
    NotANumber,
}

/// The number `raw` spells (as sent: not percent-decoded), if it is spelled canonically.
///
/// # Errors
/// [`NotCanonical::OtherSpelling`] for another spelling of a number, else
/// [`NotCanonical::NotANumber`].
pub fn parse<T: FromStr>(raw: &str) -> Result<T, NotCanonical> {
    let bytes = raw.as_bytes();
    if !bytes.is_empty()
        && bytes.iter().all(u8::is_ascii_digit)
        && (bytes[0] != b'0' || bytes.len() == 1)
    {
        return raw.parse().map_err(|_| NotCanonical::NotANumber);
    }
    if spells_a_number(raw) {
        Err(NotCanonical::OtherSpelling)
    } else {
        Err(NotCanonical::NotANumber)
    }
}

/// Whether `raw`, once percent-decoded, is what `str::parse` reads as an unsigned number: an
/// optional `+`, then digits.
fn spells_a_number(raw: &str) -> bool {
    let mut digits = 0usize;
    let mut bytes = raw.bytes();
    let mut first = true;
    while let Some(b) = bytes.next() {
        let c = if b == b'%' {
            let hi = bytes.next().and_then(|h| (h as char).to_digit(16));
            let lo = bytes.next().and_then(|l| (l as char).to_digit(16));
            match (hi, lo) {
                (Some(hi), Some(lo)) => (hi * 16 + lo) as u8,
                _ => return false,
            }
        } else {
            b
        };
        match c {
            b'+' if first => {}
            b'0'..=b'9' => digits += 1,
            _ => return false,
        }
        first = false;
    }
    digits > 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_canonical_spelling_is_a_number() {
        assert_eq!(parse::<u32>("0"), Ok(0));
        assert_eq!(parse::<u32>("10"), Ok(10));
        assert_eq!(parse::<u32>("4294967295"), Ok(u32::MAX));
        for other in [
            "+1", "01", "00", "%31", "%30", "1%30", "+%31", "%2B1", "000",
        ] {
            assert_eq!(
                parse::<u32>(other),
                Err(NotCanonical::OtherSpelling),
                "{other}"
            );
        }
        for not in [
            "",
            "+",
            "-1",
            "-0",
            "x",
            "1x",
            "%",
            "%3",
            "%zz",
            "1 ",
            "4294967296",
            "++1",
        ] {
            assert_eq!(parse::<u32>(not), Err(NotCanonical::NotANumber), "{not}");
        }
        assert_eq!(parse::<u8>("256"), Err(NotCanonical::NotANumber));
    }
}
