//! A bounds-checked little-endian reader for our binary records (the tracker window on
//! `/slam/window`, map checkpoints): every read is checked against the bytes left, and array
//! counts are checked before anything is allocated, so a damaged record cannot ask for more
//! memory than it holds. A failed read is an [`LeError`] naming the byte offset.

/// Errors of the `le` module: a read that the bytes left cannot satisfy.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LeError {
    /// Fewer bytes are left than a read needs.
    #[error("truncated at byte {at} of {len}")]
    Truncated { at: usize, len: usize },
    /// An array count whose items cannot fit in the bytes left.
    #[error("an array of {count} items at byte {at} does not fit the {left} bytes left")]
    ArrayTooLong { count: u64, at: usize, left: usize },
    /// A word count whose byte size overflows `usize`.
    #[error("word count {count} overflows")]
    WordCountOverflow { count: usize },
}

pub struct LeReader<'a> {
    data: &'a [u8],
    at: usize,
}

impl<'a> LeReader<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        LeReader { data, at: 0 }
    }

    /// Bytes read so far.
    pub fn position(&self) -> usize {
        self.at
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.data.len() - self.at
    }

    pub fn take(&mut self, n: usize) -> Result<&'a [u8], LeError> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.data.len()).ok_or(LeError::Truncated { at: self.at, len: self.data.len() })?;
        let s = &self.data[self.at..end];
        self.at = end;
        Ok(s)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], LeError> {
        Ok(self.take(N)?.try_into().expect("take returns N bytes"))
    }

    pub fn u8(&mut self) -> Result<u8, LeError> {
        Ok(self.array::<1>()?[0])
    }
    pub fn u32(&mut self) -> Result<u32, LeError> {
        self.array().map(u32::from_le_bytes)
    }
    pub fn u64(&mut self) -> Result<u64, LeError> {
        self.array().map(u64::from_le_bytes)
    }
    pub fn i64(&mut self) -> Result<i64, LeError> {
        self.array().map(i64::from_le_bytes)
    }
    pub fn f64(&mut self) -> Result<f64, LeError> {
        self.array().map(f64::from_le_bytes)
    }

    /// A `u64` count of items of `width` bytes each, refused when they cannot fit in what is
    /// left.
    pub fn count(&mut self, width: usize) -> Result<usize, LeError> {
        let n = self.u64()?;
        if n.saturating_mul(width as u64) > self.remaining() as u64 {
            return Err(LeError::ArrayTooLong { count: n, at: self.at, left: self.remaining() });
        }
        Ok(n as usize)
    }

    /// `n` little-endian `u32` words.
    pub fn words(&mut self, n: usize) -> Result<impl Iterator<Item = u32> + 'a, LeError> {
        let bytes = self.take(n.checked_mul(4).ok_or(LeError::WordCountOverflow { count: n })?)?;
        Ok(bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_in_order_and_refuses_what_is_not_there() {
        let mut b = Vec::new();
        b.push(7u8);
        b.extend_from_slice(&0xdead_beefu32.to_le_bytes());
        b.extend_from_slice(&(-5i64).to_le_bytes());
        b.extend_from_slice(&2.5f64.to_le_bytes());
        b.extend_from_slice(&2u64.to_le_bytes());
        b.extend_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&9u32.to_le_bytes());
        let mut r = LeReader::new(&b);
        assert_eq!((r.u8().unwrap(), r.u32().unwrap(), r.i64().unwrap(), r.f64().unwrap()), (7, 0xdead_beef, -5, 2.5));
        let n = r.count(4).unwrap();
        assert_eq!(r.words(n).unwrap().collect::<Vec<_>>(), vec![1, 9]);
        assert_eq!(r.remaining(), 0);
        assert!(r.u8().unwrap_err().to_string().contains("truncated at byte 37 of 37"));
        let mut huge = 0u64.wrapping_sub(1).to_le_bytes().to_vec();
        huge.extend_from_slice(&[0; 8]);
        assert!(LeReader::new(&huge).count(4).unwrap_err().to_string().contains("does not fit"));
    }
}
