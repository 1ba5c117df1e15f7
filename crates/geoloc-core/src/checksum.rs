//! Checksums of the files geoloc writes (map files, frame streams): FNV-1a, 64 bit.
//!
//! FNV-1a detects truncation and bit flips (every byte changes the state through a bijection,
//! so a single flipped byte always changes the hash); it is not a cryptographic hash and is not
//! meant to resist deliberate forgery.

/// FNV-1a, 64 bit: a fast, dependency-free checksum (not a cryptographic hash).
#[derive(Clone, Copy, Debug)]
pub struct Fnv1a(u64);

impl Fnv1a {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;

    /// The hash so far.
    pub fn finish(self) -> u64 {
        self.0
    }

    /// The hash of nothing.
    pub fn new() -> Self {
        Self(Self::OFFSET)
    }

    /// Feeds `bytes`.
    pub fn update(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(Self::PRIME);
        }
    }

    /// Hashes a length-prefixed field, so field boundaries cannot shift unnoticed.
    pub fn field(&mut self, bytes: &[u8]) {
        self.update(&(bytes.len() as u64).to_le_bytes());
        self.update(bytes);
    }
}

impl Default for Fnv1a {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        // Reference values of the FNV-1a 64-bit specification (Fowler, Noll, Vo).
        assert_eq!(Fnv1a::new().finish(), 0xcbf2_9ce4_8422_2325);
        let mut h = Fnv1a::new();
        h.update(b"a");
        assert_eq!(h.finish(), 0xaf63_dc4c_8601_ec8c);
        let mut h = Fnv1a::new();
        h.update(b"foobar");
        assert_eq!(h.finish(), 0x8594_4171_f739_67e8);
    }
}
