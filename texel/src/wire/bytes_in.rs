//! Bounded little-endian reading of one message body: every count is checked against
//! the bytes that are actually there before anything is allocated for it.

use super::WireError;

/// A cursor over one complete message body.
pub(crate) struct BodyReader<'a> {
    body: &'a [u8],
    at: usize,
    /// The message being read, for error messages.
    what: &'static str,
}

impl<'a> BodyReader<'a> {
    pub(crate) fn new(body: &'a [u8], what: &'static str) -> Self {
        Self { body, at: 0, what }
    }

    pub(crate) fn remaining(&self) -> usize {
        self.body.len() - self.at
    }

    fn short(&self, field: &'static str, need: usize) -> WireError {
        WireError::invalid(
            self.what,
            format!(
                "{field}: needs {need} bytes at body offset {}, only {} remain",
                self.at,
                self.remaining()
            ),
        )
    }

    pub(crate) fn take(&mut self, n: usize, field: &'static str) -> Result<&'a [u8], WireError> {
        if n > self.remaining() {
            return Err(self.short(field, n));
        }
        let out = &self.body[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], WireError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, field)?);
        Ok(out)
    }

    pub(crate) fn u8(&mut self, field: &'static str) -> Result<u8, WireError> {
        Ok(self.array::<1>(field)?[0])
    }

    pub(crate) fn u16(&mut self, field: &'static str) -> Result<u16, WireError> {
        Ok(u16::from_le_bytes(self.array(field)?))
    }

    pub(crate) fn u32(&mut self, field: &'static str) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }

    pub(crate) fn u64(&mut self, field: &'static str) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(self.array(field)?))
    }

    pub(crate) fn f32(&mut self, field: &'static str) -> Result<f32, WireError> {
        Ok(f32::from_le_bytes(self.array(field)?))
    }

    pub(crate) fn f64(&mut self, field: &'static str) -> Result<f64, WireError> {
        Ok(f64::from_le_bytes(self.array(field)?))
    }

    /// A count of elements of `elem_size` bytes each, refused when it exceeds `max`
    /// or the bytes left in the body (so no allocation can outgrow the message).
    pub(crate) fn count(
        &mut self,
        field: &'static str,
        elem_size: usize,
        max: usize,
    ) -> Result<usize, WireError> {
        let n = self.u32(field)? as usize;
        if n > max {
            return Err(WireError::invalid(
                self.what,
                format!("{field}: count {n} exceeds the limit {max}"),
            ));
        }
        let bytes = n.saturating_mul(elem_size);
        if bytes > self.remaining() {
            return Err(self.short(field, bytes));
        }
        Ok(n)
    }

    /// A length-prefixed UTF-8 string of at most `max` bytes.
    pub(crate) fn string(&mut self, field: &'static str, max: usize) -> Result<String, WireError> {
        let n = self.count(field, 1, max)?;
        let bytes = self.take(n, field)?;
        std::str::from_utf8(bytes)
            .map(str::to_string)
            .map_err(|_| WireError::invalid(self.what, format!("{field}: not UTF-8")))
    }

    /// `n` elements decoded by `read`, allocated only after the count was checked.
    pub(crate) fn vec<T>(
        &mut self,
        n: usize,
        field: &'static str,
        elem_size: usize,
        mut read: impl FnMut(&mut Self) -> Result<T, WireError>,
    ) -> Result<Vec<T>, WireError> {
        if n.saturating_mul(elem_size) > self.remaining() {
            return Err(self.short(field, n.saturating_mul(elem_size)));
        }
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            out.push(read(self)?);
        }
        Ok(out)
    }

    /// Fails unless the whole body was consumed.
    pub(crate) fn finish(self) -> Result<(), WireError> {
        if self.remaining() != 0 {
            return Err(WireError::invalid(
                self.what,
                format!("{} unexpected bytes after the last field", self.remaining()),
            ));
        }
        Ok(())
    }
}

/// Little-endian writing helpers.
pub(crate) trait PutLe {
    fn put_u8(&mut self, v: u8);
    fn put_u16(&mut self, v: u16);
    fn put_u32(&mut self, v: u32);
    fn put_u64(&mut self, v: u64);
    fn put_f32(&mut self, v: f32);
    fn put_f64(&mut self, v: f64);
    /// Length-prefixed bytes (the caller has checked the length fits its limit).
    fn put_bytes(&mut self, v: &[u8]);
}

impl PutLe for Vec<u8> {
    fn put_u8(&mut self, v: u8) {
        self.push(v);
    }
    fn put_u16(&mut self, v: u16) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn put_u32(&mut self, v: u32) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn put_u64(&mut self, v: u64) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn put_f32(&mut self, v: f32) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn put_f64(&mut self, v: f64) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn put_bytes(&mut self, v: &[u8]) {
        self.put_u32(u32::try_from(v.len()).unwrap_or(u32::MAX));
        self.extend_from_slice(v);
    }
}
