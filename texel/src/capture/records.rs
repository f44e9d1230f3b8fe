//! The MCAP record layer under the capture reader: frames records out of any byte
//! stream, decodes each chunk whole and CRC-checked before any of its messages is
//! yielded, and recovers around damage. A chunk whose contents are damaged is skipped
//! by its length; damaged framing (a length past the end of the file, a chunk whose
//! header disagrees with its length) is skipped by scanning for the next chunk that
//! checks out. What was lost is reported as a byte range and, where known, the log
//! times of the messages it held; damage with nothing readable after it in a file
//! without its end is a truncated recording.

use std::collections::{BTreeSet, VecDeque};
use std::io::Read;

use mcap::read::ChannelAccumulator;
use mcap::records::{ChunkHeader, Record, op};

use super::summary::SummaryIndex;

/// Bytes of the fixed part of a record: opcode `u8`, length `u64`.
const RECORD_PREFIX: usize = 9;
/// A chunk body's fixed fields before its compression string: start and end time,
/// uncompressed size (`u64` each), uncompressed CRC (`u32`), the string's length
/// (`u32`).
const CHUNK_FIXED: usize = 8 + 8 + 8 + 4 + 4;
/// Compression names are short ("zstd", "lz4"); a longer one is damage.
const MAX_COMPRESSION_NAME: usize = 16;
/// How much is read from the source at a time.
const READ_STEP: usize = 1 << 20;

/// A stretch of the file that could not be read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Damage {
    /// File offset of the first byte skipped.
    pub offset: u64,
    /// File offset after the last byte skipped.
    pub end: u64,
    /// The log times of the messages lost with it, where the file says (a chunk's
    /// header, the summary's chunk index) or the neighbouring messages bound them.
    pub lost_log_time_ns: Option<(u64, u64)>,
    pub reason: String,
}

/// What the record layer yields next.
pub enum Step {
    Message(mcap::Message<'static>),
    Damaged(Damage),
    /// The file ended where it should (its footer and closing magic, or an
    /// unchunked stream's end after its data-end record).
    End,
    /// The file ends without its footer: a recording cut short. Everything before
    /// the cut that checked out was yielded.
    Truncated,
    Io(std::io::Error),
}

/// A byte stream with a window that can be looked at before it is consumed.
struct Window<R> {
    source: R,
    buf: Vec<u8>,
    /// Index into `buf` of the first unconsumed byte.
    pos: usize,
    /// File offset of `buf[0]`.
    base: u64,
    eof: bool,
}

impl<R: Read> Window<R> {
    fn offset(&self) -> u64 {
        self.base + self.pos as u64
    }

    fn available(&self) -> usize {
        self.buf.len() - self.pos
    }

    fn bytes_read(&self) -> u64 {
        self.base + self.buf.len() as u64
    }

    /// Buffers `n` bytes from the current position; false when the stream ends first.
    /// Consumed bytes are dropped once they are half the buffer, so each byte is
    /// moved a bounded number of times.
    fn fill(&mut self, n: usize) -> std::io::Result<bool> {
        while self.available() < n {
            if self.eof {
                return Ok(false);
            }
            if self.pos > 0 && self.pos >= self.buf.len() / 2 {
                self.buf.drain(..self.pos);
                self.base += self.pos as u64;
                self.pos = 0;
            }
            let old = self.buf.len();
            let step = (n - self.available()).clamp(64 << 10, READ_STEP);
            self.buf.resize(old + step, 0);
            let read = loop {
                match self.source.read(&mut self.buf[old..]) {
                    Ok(r) => break r,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        self.buf.truncate(old);
                        return Err(e);
                    }
                }
            };
            self.buf.truncate(old + read);
            if read == 0 {
                self.eof = true;
            }
        }
        Ok(true)
    }

    fn peek(&self, n: usize) -> &[u8] {
        let end = (self.pos + n).min(self.buf.len());
        &self.buf[self.pos..end]
    }

    fn consume(&mut self, n: usize) {
        self.pos = (self.pos + n).min(self.buf.len());
    }
}

fn u64_at(bytes: &[u8], at: usize) -> Option<u64> {
    let b: [u8; 8] = bytes.get(at..at + 8)?.try_into().ok()?;
    Some(u64::from_le_bytes(b))
}

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    let b: [u8; 4] = bytes.get(at..at + 4)?.try_into().ok()?;
    Some(u32::from_le_bytes(b))
}

/// A chunk record's header, checked against the record's length: the fields a
/// resynchronising scan trusts before it spends a decompression on a candidate.
#[derive(Debug, Clone, Copy)]
struct ChunkFrame {
    record_len: u64,
    start_time: u64,
    end_time: u64,
}

/// Why a chunk record's framing cannot be trusted, or `Ok` with its header fields.
/// `bytes` starts at the opcode; `Err(None)`: more bytes are needed to tell.
fn check_chunk_frame(bytes: &[u8], limit: u64) -> Result<ChunkFrame, Option<&'static str>> {
    let record_len = u64_at(bytes, 1).ok_or(None)?;
    let body = &bytes[RECORD_PREFIX.min(bytes.len())..];
    let start_time = u64_at(body, 0).ok_or(None)?;
    let end_time = u64_at(body, 8).ok_or(None)?;
    let uncompressed = u64_at(body, 16).ok_or(None)?;
    let name_len = u32_at(body, 28).ok_or(None)? as usize;
    if name_len > MAX_COMPRESSION_NAME {
        return Err(Some("the chunk's compression name is too long"));
    }
    let name = body.get(CHUNK_FIXED..CHUNK_FIXED + name_len).ok_or(None)?;
    if !matches!(name, b"" | b"zstd" | b"lz4") {
        return Err(Some("the chunk names an unknown compression"));
    }
    let compressed = u64_at(body, CHUNK_FIXED + name_len).ok_or(None)?;
    let header_len = (CHUNK_FIXED + name_len + 8) as u64;
    if compressed.checked_add(header_len) != Some(record_len) {
        return Err(Some("the chunk's sizes disagree with its record length"));
    }
    if record_len > limit || uncompressed > limit {
        return Err(Some(
            "the chunk claims more than any capture record may hold",
        ));
    }
    if start_time > end_time {
        return Err(Some("the chunk's message times run backwards"));
    }
    Ok(ChunkFrame {
        record_len,
        start_time,
        end_time,
    })
}

/// The records of one chunk, decompressed and CRC-checked as a whole. The output
/// grows with what the decompressor actually produces, never with what the header
/// claims, so a forged size costs nothing.
fn chunk_records(body: &[u8]) -> Result<Vec<Record<'static>>, String> {
    let (header, data) = match mcap::parse_record(op::CHUNK, body) {
        Ok(Record::Chunk { header, data }) => (header, data),
        Ok(_) => return Err("not a chunk".into()),
        Err(e) => return Err(e.to_string()),
    };
    let header: ChunkHeader = header;
    let size = usize::try_from(header.uncompressed_size)
        .map_err(|_| "the chunk's uncompressed size does not fit in memory".to_string())?;
    let owned;
    let records: &[u8] = match header.compression.as_str() {
        "" => &data,
        "zstd" => {
            let decoder = zstd::stream::read::Decoder::with_buffer(data.as_ref())
                .map_err(|e| format!("zstd: {e}"))?;
            owned = read_bounded(decoder, size).map_err(|e| format!("zstd: {e}"))?;
            &owned
        }
        "lz4" => {
            let decoder = lz4::Decoder::new(data.as_ref()).map_err(|e| format!("lz4: {e}"))?;
            owned = read_bounded(decoder, size).map_err(|e| format!("lz4: {e}"))?;
            &owned
        }
        other => return Err(format!("unknown compression {other:?}")),
    };
    if records.len() != size {
        return Err(format!(
            "{} bytes of records where the header says {size}",
            records.len()
        ));
    }
    if header.uncompressed_crc != 0 {
        let calculated = crc32fast::hash(records);
        if calculated != header.uncompressed_crc {
            return Err(format!(
                "CRC {calculated:08x} where the header says {:08x}",
                header.uncompressed_crc
            ));
        }
    }
    let mut out = Vec::new();
    let mut rest = records;
    while !rest.is_empty() {
        let (opcode, len) = match (rest.first(), u64_at(rest, 1)) {
            (Some(&opcode), Some(len)) => (opcode, len),
            _ => return Err("a record prefix is cut short at the chunk's end".into()),
        };
        let body = usize::try_from(len)
            .ok()
            .and_then(|len| rest.get(RECORD_PREFIX..RECORD_PREFIX.checked_add(len)?))
            .ok_or("a record runs past the chunk's end")?;
        let record = mcap::parse_record(opcode, body).map_err(|e| e.to_string())?;
        out.push(record.into_owned());
        rest = &rest[RECORD_PREFIX + body.len()..];
    }
    Ok(out)
}

/// Reads at most `size + 1` bytes (one more tells an overlong stream).
fn read_bounded(reader: impl Read, size: usize) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::new();
    reader
        .take(u64::try_from(size).unwrap_or(u64::MAX).saturating_add(1))
        .read_to_end(&mut out)?;
    Ok(out)
}

/// Reads records and links messages to their channels, recovering around damage.
pub struct RecordReader<R> {
    window: Window<R>,
    channels: ChannelAccumulator<'static>,
    file_len: Option<u64>,
    record_limit: u64,
    summary: Option<SummaryIndex>,
    pending: VecDeque<mcap::Message<'static>>,
    /// A damage report to yield after the messages of the chunk that ended it.
    pending_damage: Option<Damage>,
    past_data_end: bool,
    finished: bool,
    last_log_time_ns: Option<u64>,
    /// Chunk start offsets read whole, to tell which of the summary's chunks were lost.
    chunks_read: BTreeSet<u64>,
}

impl<R: Read> RecordReader<R> {
    /// `source` starts after the magic (at `offset`); `summary` (read from the file's
    /// end, when it has one) names the channels and chunks up front.
    pub fn new(
        source: R,
        offset: u64,
        file_len: Option<u64>,
        record_limit: u64,
        summary: Option<SummaryIndex>,
    ) -> Self {
        let mut channels = ChannelAccumulator::default();
        if let Some(s) = &summary {
            s.seed(&mut channels);
        }
        Self {
            window: Window {
                source,
                buf: Vec::new(),
                pos: 0,
                base: offset,
                eof: false,
            },
            channels,
            file_len,
            record_limit,
            summary,
            pending: VecDeque::new(),
            pending_damage: None,
            past_data_end: false,
            finished: false,
            last_log_time_ns: None,
            chunks_read: BTreeSet::new(),
        }
    }

    pub fn bytes_read(&self) -> u64 {
        self.window.bytes_read()
    }

    /// The file's first `n` bytes (fewer when it is shorter), consumed.
    pub fn take_magic(&mut self, n: usize) -> std::io::Result<Vec<u8>> {
        self.window.fill(n)?;
        let head = self.window.peek(n).to_vec();
        self.window.consume(head.len());
        Ok(head)
    }

    /// How many bytes the file holds from `offset` on, where its length is known.
    fn room_after(&self, offset: u64) -> Option<u64> {
        self.file_len.map(|len| len.saturating_sub(offset))
    }

    pub fn next_step(&mut self) -> Step {
        loop {
            if let Some(message) = self.pending.pop_front() {
                self.last_log_time_ns = Some(message.log_time);
                return Step::Message(message);
            }
            if let Some(damage) = self.pending_damage.take() {
                return Step::Damaged(damage);
            }
            if self.finished {
                return Step::End;
            }
            match self.next_record() {
                Ok(Some(step)) => return step,
                Ok(None) => {}
                Err(e) => {
                    self.finished = true;
                    return Step::Io(e);
                }
            }
        }
    }

    /// Reads one record; `None` when it only fed the pending messages or was skipped.
    fn next_record(&mut self) -> std::io::Result<Option<Step>> {
        let start = self.window.offset();
        if !self.window.fill(RECORD_PREFIX)? {
            return Ok(Some(self.end_of_data(start)));
        }
        let prefix = self.window.peek(RECORD_PREFIX);
        let opcode = prefix[0];
        let len = u64_at(prefix, 1).unwrap_or(u64::MAX);
        let fits_file = self
            .room_after(start)
            .is_none_or(|room| len.saturating_add(RECORD_PREFIX as u64) <= room);
        if len > self.record_limit || !fits_file {
            let reason = if fits_file {
                "a record claims more than any capture record may hold"
            } else {
                "a record claims more bytes than the file holds"
            };
            return self.recover(start, reason);
        }
        let total = RECORD_PREFIX + len as usize;
        if !self.window.fill(total)? {
            return self.recover(start, "the file ends inside a record");
        }
        if self.past_data_end {
            // The summary repeats what the data section said: framed, not re-read.
            self.window.consume(total);
            if opcode == op::FOOTER {
                return Ok(Some(self.closing_magic()?));
            }
            return Ok(None);
        }
        match opcode {
            op::CHUNK => {
                let frame = check_chunk_frame(self.window.peek(total), self.record_limit);
                let frame = match frame {
                    Ok(f) => f,
                    Err(why) => {
                        let reason = why.unwrap_or("the chunk header is cut short");
                        return self.recover(start, reason);
                    }
                };
                let body = &self.window.peek(total)[RECORD_PREFIX..];
                let decoded = chunk_records(body);
                self.window.consume(total);
                match decoded.and_then(|records| self.link(records)) {
                    Ok(()) => {
                        self.chunks_read.insert(start);
                        Ok(None)
                    }
                    Err(reason) => Ok(Some(Step::Damaged(Damage {
                        offset: start,
                        end: start + total as u64,
                        lost_log_time_ns: self
                            .summary_times(start, start + total as u64)
                            .or(Some((frame.start_time, frame.end_time))),
                        reason: format!("a damaged chunk: {reason}"),
                    }))),
                }
            }
            op::SCHEMA | op::CHANNEL | op::MESSAGE => {
                let record = mcap::parse_record(opcode, &self.window.peek(total)[RECORD_PREFIX..])
                    .map(Record::into_owned)
                    .map_err(|e| e.to_string());
                self.window.consume(total);
                match record.and_then(|r| self.link(vec![r])) {
                    Ok(()) => Ok(None),
                    Err(reason) => Ok(Some(Step::Damaged(Damage {
                        offset: start,
                        end: start + total as u64,
                        lost_log_time_ns: None,
                        reason: format!("a damaged record: {reason}"),
                    }))),
                }
            }
            op::DATA_END => {
                self.window.consume(total);
                self.past_data_end = true;
                Ok(None)
            }
            op::FOOTER => {
                self.window.consume(total);
                Ok(Some(self.closing_magic()?))
            }
            // Headers, indexes, attachments, metadata and records of later versions
            // of the format carry no messages: skipped by their length.
            _ => {
                self.window.consume(total);
                Ok(None)
            }
        }
    }

    /// Adds a chunk's (or a lone record's) schemas and channels and queues its
    /// messages; a record that does not link fails the whole batch.
    fn link(&mut self, records: Vec<Record<'static>>) -> Result<(), String> {
        let mut messages = Vec::new();
        for record in records {
            match record {
                Record::Schema { header, data } => self
                    .channels
                    .add_schema(header, data)
                    .map_err(|e| e.to_string())?,
                Record::Channel(channel) => self
                    .channels
                    .add_channel(channel)
                    .map_err(|e| e.to_string())?,
                Record::Message { header, data } => {
                    let channel = self.channels.get(header.channel_id).ok_or_else(|| {
                        format!(
                            "a message on channel {} that no readable record defines",
                            header.channel_id
                        )
                    })?;
                    messages.push(mcap::Message {
                        channel,
                        sequence: header.sequence,
                        log_time: header.log_time,
                        publish_time: header.publish_time,
                        data,
                    });
                }
                _ => {}
            }
        }
        self.pending.extend(messages);
        Ok(())
    }

    /// After the footer: the closing magic, else the file was cut in its last bytes.
    fn closing_magic(&mut self) -> std::io::Result<Step> {
        self.finished = true;
        let magic = super::reader::MCAP_MAGIC;
        if !self.window.fill(magic.len())? {
            return Ok(Step::Truncated);
        }
        if self.window.peek(magic.len()) != magic {
            self.pending_damage = Some(Damage {
                offset: self.window.offset(),
                end: self.window.offset() + magic.len() as u64,
                lost_log_time_ns: None,
                reason: "the closing magic is damaged".into(),
            });
        }
        Ok(self.report_unread_chunks())
    }

    /// The stream ended at a record boundary or inside a record prefix.
    fn end_of_data(&mut self, _at: u64) -> Step {
        self.finished = true;
        Step::Truncated
    }

    /// Chunks the summary lists that were never read whole (a damaged opcode, a
    /// region skipped by a scan): their times are lost too. Reported once, at the end.
    fn report_unread_chunks(&mut self) -> Step {
        let Some(summary) = &self.summary else {
            return Step::End;
        };
        let unread: Vec<_> = summary
            .chunks
            .iter()
            .filter(|c| !self.chunks_read.contains(&c.offset))
            .collect();
        let (Some(first), Some(last)) = (unread.first(), unread.last()) else {
            return Step::End;
        };
        let damage = Damage {
            offset: first.offset,
            end: last.offset.saturating_add(last.length),
            lost_log_time_ns: Some((
                unread.iter().map(|c| c.start_time).min().unwrap_or(0),
                unread.iter().map(|c| c.end_time).max().unwrap_or(0),
            )),
            reason: format!(
                "{} chunk(s) the summary lists were not readable",
                unread.len()
            ),
        };
        // Only report what was not already reported as damage on the way.
        self.chunks_read.extend(unread.iter().map(|c| c.offset));
        if self.pending_damage.is_none() {
            self.pending_damage = Some(damage);
        }
        Step::End
    }

    /// The log times of the summary's chunks that start in `[from, to)`.
    fn summary_times(&self, from: u64, to: u64) -> Option<(u64, u64)> {
        let summary = self.summary.as_ref()?;
        let chunks: Vec<_> = summary
            .chunks
            .iter()
            .filter(|c| c.offset >= from && c.offset < to)
            .collect();
        Some((
            chunks.iter().map(|c| c.start_time).min()?,
            chunks.iter().map(|c| c.end_time).max()?,
        ))
    }

    /// Damaged framing at `start`: scans forward for the next chunk that checks out
    /// and reports the bytes in between. With nothing readable after the damage, a
    /// file without its summary is a truncated recording.
    fn recover(&mut self, start: u64, reason: &str) -> std::io::Result<Option<Step>> {
        self.window.consume(1);
        loop {
            let Some(found) = self.scan_for_chunk()? else {
                self.finished = true;
                if self.summary.is_none() || self.past_data_end {
                    return Ok(Some(Step::Truncated));
                }
                let end = self.window.offset();
                self.mark_summary_chunks_in(start, end);
                return Ok(Some(Step::Damaged(Damage {
                    offset: start,
                    end,
                    lost_log_time_ns: self
                        .summary_times(start, end)
                        .or(self.last_log_time_ns.map(|t| (t, u64::MAX))),
                    reason: format!("{reason}; nothing readable after it"),
                })));
            };
            let total = RECORD_PREFIX + found.record_len as usize;
            let body = &self.window.peek(total)[RECORD_PREFIX..];
            let Ok(records) = chunk_records(body) else {
                // A chunk-like pattern that does not decode: go on past its first byte.
                self.window.consume(1);
                continue;
            };
            let end = self.window.offset();
            // The messages lost lie between the last one read and this chunk's first.
            let lost = self
                .summary_times(start, end)
                .or_else(|| Some((self.last_log_time_ns.unwrap_or(0), found.start_time)));
            self.mark_summary_chunks_in(start, end);
            self.window.consume(total);
            if let Err(why) = self.link(records) {
                // A chunk that decodes but whose channels were lost with the damage.
                return Ok(Some(Step::Damaged(Damage {
                    offset: start,
                    end: end + total as u64,
                    lost_log_time_ns: lost.map(|(a, _)| (a, found.end_time)),
                    reason: format!("{reason}; then {why}"),
                })));
            }
            self.chunks_read.insert(end);
            return Ok(Some(Step::Damaged(Damage {
                offset: start,
                end,
                lost_log_time_ns: lost,
                reason: reason.to_string(),
            })));
        }
    }

    /// The summary's chunks inside a reported region count as reported.
    fn mark_summary_chunks_in(&mut self, from: u64, to: u64) {
        if let Some(summary) = &self.summary {
            self.chunks_read.extend(
                summary
                    .chunks
                    .iter()
                    .filter(|c| c.offset >= from && c.offset < to)
                    .map(|c| c.offset),
            );
        }
    }

    /// Moves the window to the next chunk record whose framing checks out (buffered
    /// whole), or to the end of the stream (`None`).
    fn scan_for_chunk(&mut self) -> std::io::Result<Option<ChunkFrame>> {
        let header_max = RECORD_PREFIX + CHUNK_FIXED + MAX_COMPRESSION_NAME + 8;
        loop {
            if !self.window.fill(1)? {
                return Ok(None);
            }
            let view = self.window.peek(self.window.available());
            let Some(skip) = view.iter().position(|&b| b == op::CHUNK) else {
                let n = view.len();
                self.window.consume(n);
                continue;
            };
            self.window.consume(skip);
            // Enough bytes to judge the header (fewer only at the end of the file).
            self.window.fill(header_max)?;
            let offset = self.window.offset();
            match check_chunk_frame(self.window.peek(header_max), self.record_limit) {
                Ok(frame)
                    if self.room_after(offset).is_none_or(|room| {
                        frame.record_len.saturating_add(RECORD_PREFIX as u64) <= room
                    }) =>
                {
                    let total = RECORD_PREFIX + frame.record_len as usize;
                    if self.window.fill(total)? {
                        return Ok(Some(frame));
                    }
                }
                _ => {}
            }
            self.window.consume(1);
        }
    }
}
