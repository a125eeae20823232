//! Tagged sections: the payload of every record written since kinds 12–14 (the crate root's
//! file layout says which record holds which section).
//!
//! A payload is a sequence of sections, each `tag: u32, length: u64, bytes` (little-endian),
//! whose bytes are one value encoded by [`super::codec`]. A new field of a record is a new
//! section, not a new record kind: a record is written with the sections its rig has, and a
//! reader takes those it knows.
//!
//! Bit 31 of a tag ([`OPTIONAL`]) says that a reader which does not know the section may skip
//! it (something a later build adds that an older one can do without, such as a cache or a
//! note); a tag without it that the reader does not know makes the record unreadable, since
//! the rig it would make is not the one that was stored. Every section of this build has the
//! bit clear: it knows them all.
//!
//! [`Sections::parse`] checks the framing before anything is decoded: each section header
//! fits in the payload, each length runs no further than the payload's end (checked before it
//! is used as a size: a length never allocates), no tag appears twice, every tag without
//! [`OPTIONAL`] is one this kind of record holds, and every section the kind requires is
//! there. The sections are then views of the payload, decoded one by one.

use std::collections::HashSet;
use std::io::Write;

use serde::Serialize;
use serde::de::DeserializeOwned;

use super::codec;

/// Bit of a tag: a reader that does not know the section skips it instead of refusing the
/// record.
pub const OPTIONAL: u32 = 1 << 31;
/// Bytes of a section's header: tag and length.
pub const SECTION_HEADER: usize = 4 + 8;

/// A section this build knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Known {
    /// Its tag.
    pub tag: u32,
    /// Its name, for problems.
    pub name: &'static str,
    /// Whether every record of a kind that may hold it must.
    pub required: bool,
}

/// Writes one section: its tag, its length, then `value` encoded by [`codec`]. The value is
/// encoded twice, once to count its bytes (the length goes first) and once into `w`, so it is
/// never held in memory as bytes.
pub fn write<T: Serialize, W: Write>(w: &mut W, tag: u32, value: &T) -> Result<(), String> {
    let len = codec::stored_len(value).map_err(|e| e.to_string())?;
    w.write_all(&tag.to_le_bytes())
        .and_then(|()| w.write_all(&len.to_le_bytes()))
        .map_err(|e| e.to_string())?;
    let wrote = codec::to_stored_writer(value, w).map_err(|e| e.to_string())?;
    if wrote as u64 != len {
        return Err(format!(
            "section {tag:#x} encoded to {wrote} bytes after counting {len}"
        ));
    }
    Ok(())
}

/// The sections of one payload, checked (module doc), as views of it.
#[derive(Debug)]
pub struct Sections<'a> {
    /// What the record is, for problems ("rig record").
    what: &'static str,
    /// The known sections found, with their bytes.
    found: Vec<(Known, &'a [u8])>,
}

impl<'a> Sections<'a> {
    /// Splits `payload` into sections, checking it against `known`, the sections a `what`
    /// may hold. Fails, with the problem, on anything the module doc says a reader refuses.
    pub fn parse(
        payload: &'a [u8],
        what: &'static str,
        known: &[Known],
    ) -> Result<Sections<'a>, String> {
        let mut found: Vec<(Known, &'a [u8])> = Vec::new();
        let mut seen = HashSet::new();
        let mut at = 0usize;
        while at < payload.len() {
            let rest = &payload[at..];
            let Some((head, rest)) = rest.split_at_checked(SECTION_HEADER) else {
                return Err(format!(
                    "{what}: truncated section header at byte {at} ({} bytes left, a header \
                     is {SECTION_HEADER})",
                    rest.len()
                ));
            };
            let mut tag = [0u8; 4];
            tag.copy_from_slice(&head[..4]);
            let tag = u32::from_le_bytes(tag);
            let mut len = [0u8; 8];
            len.copy_from_slice(&head[4..]);
            let len = u64::from_le_bytes(len);
            if len > rest.len() as u64 {
                return Err(format!(
                    "{what}: section {tag:#x} at byte {at} says {len} bytes, the payload has \
                     {} after its header",
                    rest.len()
                ));
            }
            // In range: len <= rest.len(), a usize.
            let len = len as usize;
            if !seen.insert(tag) {
                return Err(format!("{what}: section {tag:#x} appears twice"));
            }
            match known.iter().find(|k| k.tag == tag) {
                Some(k) => found.push((*k, &rest[..len])),
                None if tag & OPTIONAL != 0 => {
                    tracing::debug!(tag, "skipping an optional section this build does not know");
                }
                None => {
                    return Err(format!(
                        "{what}: unknown section {tag:#x} that is not optional (written by a \
                         newer build?)"
                    ));
                }
            }
            at += SECTION_HEADER + len;
        }
        if let Some(k) = known
            .iter()
            .find(|k| k.required && !found.iter().any(|(f, _)| f.tag == k.tag))
        {
            return Err(format!("{what}: no {} section", k.name));
        }
        Ok(Sections { what, found })
    }

    /// Decodes section `k` when the payload has it (once: it is taken).
    pub fn take<T: DeserializeOwned>(&mut self, k: Known) -> Result<Option<T>, String> {
        let Some(i) = self.found.iter().position(|(f, _)| f.tag == k.tag) else {
            return Ok(None);
        };
        let (_, bytes) = self.found.swap_remove(i);
        codec::from_stored(bytes)
            .map(Some)
            .map_err(|e| format!("{}: {} section: {e}", self.what, k.name))
    }

    /// [`Sections::take`] for a value that borrows from the payload ([`codec::from_stored_borrowed`]).
    pub fn take_borrowed<T: serde::Deserialize<'a>>(
        &mut self,
        k: Known,
    ) -> Result<Option<T>, String> {
        let Some(i) = self.found.iter().position(|(f, _)| f.tag == k.tag) else {
            return Ok(None);
        };
        let (_, bytes) = self.found.swap_remove(i);
        codec::from_stored_borrowed(bytes)
            .map(Some)
            .map_err(|e| format!("{}: {} section: {e}", self.what, k.name))
    }

    /// Decodes section `k`, which the payload must have.
    pub fn require<T: DeserializeOwned>(&mut self, k: Known) -> Result<T, String> {
        self.take(k)?
            .ok_or_else(|| format!("{}: no {} section", self.what, k.name))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: Known = Known {
        tag: 1,
        name: "a",
        required: true,
    };
    const B: Known = Known {
        tag: 2,
        name: "b",
        required: false,
    };
    const KNOWN: &[Known] = &[A, B];

    fn raw(tag: u32, bytes: &[u8]) -> Vec<u8> {
        let mut out = tag.to_le_bytes().to_vec();
        out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        out.extend_from_slice(bytes);
        out
    }

    fn section<T: Serialize>(tag: u32, value: &T) -> Vec<u8> {
        let mut out = Vec::new();
        write(&mut out, tag, value).expect("write");
        out
    }

    fn parse(payload: &[u8]) -> Result<(String, Option<Vec<u32>>), String> {
        let mut s = Sections::parse(payload, "test record", KNOWN)?;
        Ok((s.require(A)?, s.take(B)?))
    }

    #[test]
    fn sections_read_back_in_any_order_and_optional_ones_may_be_absent() {
        let a = section(A.tag, &"hello");
        let b = section(B.tag, &vec![1u32, 2, 3]);
        assert_eq!(
            parse(&[a.clone(), b.clone()].concat()),
            Ok(("hello".into(), Some(vec![1, 2, 3])))
        );
        assert_eq!(
            parse(&[b, a.clone()].concat()),
            Ok(("hello".into(), Some(vec![1, 2, 3])))
        );
        assert_eq!(parse(&a), Ok(("hello".into(), None)));
        // The header is the tag and the length, little-endian.
        assert_eq!(&a[..4], &1u32.to_le_bytes());
        assert_eq!(a.len(), SECTION_HEADER + 6);
        assert_eq!(&a[4..12], &6u64.to_le_bytes());
    }

    #[test]
    fn an_unknown_optional_section_is_skipped_and_an_unknown_required_one_refused() {
        let a = section(A.tag, &"x");
        let later = raw(OPTIONAL | 77, &[9; 40]);
        let empty = raw(OPTIONAL | 78, &[]);
        assert_eq!(
            parse(&[later.clone(), a.clone(), empty].concat()),
            Ok(("x".into(), None))
        );
        // The same tag without the bit must be understood.
        let e = parse(&[a.clone(), raw(77, &[9; 40])].concat()).expect_err("refused");
        assert!(
            e.contains("unknown section 0x4d") && e.contains("not optional"),
            "{e}"
        );
        // An optional section twice is as wrong as a known one twice.
        let e = parse(&[later.clone(), a.clone(), later].concat()).expect_err("refused");
        assert!(e.contains("appears twice"), "{e}");
    }

    #[test]
    fn bad_framing_is_refused_with_a_problem() {
        let a = section(A.tag, &"x");
        let b = section(B.tag, &vec![5u32]);
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (Vec::new(), "no a section"),
            (b.clone(), "no a section"),
            ([a.clone(), a.clone()].concat(), "appears twice"),
            (
                [a.clone(), b[..7].to_vec()].concat(),
                "truncated section header",
            ),
            (
                [a.clone(), b[..b.len() - 1].to_vec()].concat(),
                "says 2 bytes",
            ),
            (
                [a.clone(), raw(B.tag, &[]), vec![0xff; 3]].concat(),
                "truncated section header",
            ),
        ];
        for (payload, want) in cases {
            let e = parse(&payload).expect_err("refused");
            assert!(e.contains(want), "{e:?} does not say {want:?}");
        }
        // A length near u64::MAX is refused before it is used as a size.
        let mut huge = a.clone();
        huge.extend_from_slice(&B.tag.to_le_bytes());
        huge.extend_from_slice(&u64::MAX.to_le_bytes());
        let e = parse(&huge).expect_err("refused");
        assert!(e.contains(&format!("says {} bytes", u64::MAX)), "{e}");
        // A section whose bytes are not its value.
        let e = parse(&[a, raw(B.tag, &[1, 2, 3])].concat()).expect_err("refused");
        assert!(e.contains("b section"), "{e}");
    }

    #[test]
    fn a_known_section_of_another_kind_of_record_is_refused() {
        let a = section(A.tag, &"x");
        let e = Sections::parse(&[a.clone(), raw(3, &[])].concat(), "test record", KNOWN)
            .map(|_| ())
            .expect_err("refused");
        assert!(e.contains("unknown section 0x3"), "{e}");
        assert!(Sections::parse(&a, "test record", KNOWN).is_ok());
    }
}
