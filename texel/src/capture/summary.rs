//! A capture's summary section, read from the end of the file before its data: the
//! schemas and channels (so a chunk read after damage still links its messages) and
//! the chunk index (so what damage cost is told in log times). A summary that is
//! missing, cut or fails its CRC is simply not used.

use std::borrow::Cow;
use std::io::{Read, Seek, SeekFrom};

use mcap::read::ChannelAccumulator;
use mcap::records::{Record, SchemaHeader, op};

/// The footer record (opcode, length, summary start, summary offset start, CRC) and
/// the closing magic.
const FOOTER_RECORD_LEN: u64 = 1 + 8 + 8 + 8 + 4;
const TAIL_LEN: u64 = FOOTER_RECORD_LEN + 8;
/// Larger summaries are not read (a capture of hours has a few thousand chunks, far
/// below this).
const MAX_SUMMARY_LEN: u64 = 64 << 20;

/// Where one chunk lies and the log times of its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChunkSpan {
    pub offset: u64,
    pub length: u64,
    pub start_time: u64,
    pub end_time: u64,
}

/// What the summary section says, as far as reading around damage needs it.
#[derive(Debug, Default)]
pub struct SummaryIndex {
    schemas: Vec<(SchemaHeader, Vec<u8>)>,
    channels: Vec<mcap::records::Channel>,
    pub chunks: Vec<ChunkSpan>,
}

impl SummaryIndex {
    /// Reads the summary of a file of `file_len` bytes; `None` when it has none or
    /// it does not check out.
    pub fn read<F: Read + Seek>(file: &mut F, file_len: u64) -> Option<Self> {
        let footer_start = file_len.checked_sub(TAIL_LEN)?;
        let mut tail = [0u8; TAIL_LEN as usize];
        file.seek(SeekFrom::Start(footer_start)).ok()?;
        file.read_exact(&mut tail).ok()?;
        if &tail[FOOTER_RECORD_LEN as usize..] != super::reader::MCAP_MAGIC
            || tail[0] != op::FOOTER
            || u64::from_le_bytes(tail[1..9].try_into().ok()?) != FOOTER_RECORD_LEN - 9
        {
            return None;
        }
        let summary_start = u64::from_le_bytes(tail[9..17].try_into().ok()?);
        let crc = u32::from_le_bytes(tail[25..29].try_into().ok()?);
        if summary_start == 0 || summary_start >= footer_start {
            return None;
        }
        let len = footer_start - summary_start;
        if len > MAX_SUMMARY_LEN {
            return None;
        }
        let mut section = vec![0u8; usize::try_from(len).ok()?];
        file.seek(SeekFrom::Start(summary_start)).ok()?;
        file.read_exact(&mut section).ok()?;
        if crc != 0 {
            let mut hasher = crc32fast::Hasher::new();
            hasher.update(&section);
            hasher.update(&tail[..25]);
            if hasher.finalize() != crc {
                return None;
            }
        }
        Self::parse(&section)
    }

    fn parse(mut section: &[u8]) -> Option<Self> {
        let mut index = Self::default();
        while !section.is_empty() {
            let opcode = *section.first()?;
            let len =
                usize::try_from(u64::from_le_bytes(section.get(1..9)?.try_into().ok()?)).ok()?;
            let body = section.get(9..9usize.checked_add(len)?)?;
            match mcap::parse_record(opcode, body).ok()? {
                Record::Schema { header, data } => index.schemas.push((header, data.into_owned())),
                Record::Channel(channel) => index.channels.push(channel),
                Record::ChunkIndex(c) => index.chunks.push(ChunkSpan {
                    offset: c.chunk_start_offset,
                    length: c.chunk_length,
                    start_time: c.message_start_time,
                    end_time: c.message_end_time,
                }),
                _ => {}
            }
            section = &section[9 + len..];
        }
        Some(index)
    }

    /// Gives `channels` the summary's schemas and channels (ones that do not link are
    /// left for the data section to define).
    pub fn seed(&self, channels: &mut ChannelAccumulator<'static>) {
        for (header, data) in &self.schemas {
            let _ = channels.add_schema(header.clone(), Cow::Owned(data.clone()));
        }
        for channel in &self.channels {
            let _ = channels.add_channel(channel.clone());
        }
    }
}
