//! Pages of the per-frame tables (`texel::paged`) on disk: one unlinked file per
//! table beside the model's store, a fixed slot per page (the page, then a CRC-32 of
//! it), written and read in place. The file lives as long as the daemon; a resumed
//! session rebuilds its tables from the recording.

use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use texel::paged::{PageError, PageStore};

/// A page store in an unlinked file.
#[derive(Debug)]
pub struct FilePages {
    file: File,
    path: PathBuf,
    page_bytes: usize,
}

impl FilePages {
    /// An empty store in `dir` for pages of `page_bytes`, its file unlinked at once.
    pub fn create_in(dir: &Path, name: &str, page_bytes: usize) -> std::io::Result<Self> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let path = dir.join(format!("texel-{name}-{}-{nanos}.pages", std::process::id()));
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)?;
        std::fs::remove_file(&path)?;
        Ok(Self {
            file,
            path,
            page_bytes,
        })
    }

    fn slot(&self, page: u64) -> Result<u64, PageError> {
        page.checked_mul(self.page_bytes as u64 + 4)
            .ok_or_else(|| self.error(page, "beyond any file"))
    }

    fn error(&self, page: u64, what: impl std::fmt::Display) -> PageError {
        PageError(format!("{} page {page}: {what}", self.path.display()))
    }
}

impl PageStore for FilePages {
    fn write_page(&mut self, page: u64, bytes: &[u8]) -> Result<(), PageError> {
        if bytes.len() != self.page_bytes {
            return Err(self.error(
                page,
                format!("{} bytes, pages are {}", bytes.len(), self.page_bytes),
            ));
        }
        let mut slot = Vec::with_capacity(bytes.len() + 4);
        slot.extend_from_slice(bytes);
        slot.extend_from_slice(&crc32fast::hash(bytes).to_le_bytes());
        let at = self.slot(page)?;
        self.file
            .write_all_at(&slot, at)
            .map_err(|e| self.error(page, e))
    }

    fn read_page(&self, page: u64, out: &mut [u8]) -> Result<(), PageError> {
        if out.len() != self.page_bytes {
            return Err(self.error(
                page,
                format!(
                    "asked for {} bytes, pages are {}",
                    out.len(),
                    self.page_bytes
                ),
            ));
        }
        let at = self.slot(page)?;
        self.file
            .read_exact_at(out, at)
            .map_err(|e| self.error(page, e))?;
        let mut crc = [0u8; 4];
        self.file
            .read_exact_at(&mut crc, at + self.page_bytes as u64)
            .map_err(|e| self.error(page, e))?;
        if crc32fast::hash(out) != u32::from_le_bytes(crc) {
            return Err(self.error(page, "CRC mismatch (never written, or damaged)"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)] // tests panic on failure by design

    use super::*;
    use texel::paged::{PAGE_RECORDS, PagedTable};

    #[test]
    fn a_table_paged_to_a_file_reads_back_what_it_holds() {
        let store = FilePages::create_in(&std::env::temp_dir(), "test", PAGE_RECORDS * 8).unwrap();
        assert!(!store.path.exists(), "the file is unlinked");
        let mut table: PagedTable<u64> = PagedTable::paged(Box::new(store), 2);
        let n = 10 * PAGE_RECORDS as u64 + 17;
        for i in 0..n {
            table.push(i * 3);
        }
        assert!(table.update(5, |r| *r = 7));
        assert_eq!(table.resident_pages(), 2);
        assert_eq!(table.get(5), Some(7));
        assert_eq!(
            table.get(3 * PAGE_RECORDS + 1),
            Some((3 * PAGE_RECORDS as u64 + 1) * 3)
        );
        assert_eq!(table.get(n as usize), None);
        assert_eq!(table.errors(), 0);
    }

    #[test]
    fn unwritten_and_damaged_pages_are_errors_naming_the_page() {
        let mut store = FilePages::create_in(&std::env::temp_dir(), "test", 64).unwrap();
        let mut out = vec![0u8; 64];
        assert!(store.read_page(3, &mut out).is_err());
        store.write_page(0, &[7u8; 64]).unwrap();
        store.write_page(2, &[9u8; 64]).unwrap();
        store.read_page(2, &mut out).unwrap();
        assert_eq!(out, vec![9u8; 64]);
        // Page 1 lies in a hole between written pages: zeros, whose CRC is not zero.
        let err = store.read_page(1, &mut out).unwrap_err();
        assert!(err.0.contains("page 1") && err.0.contains("CRC"), "{err}");
        store.file.write_all_at(&[1], 10).unwrap();
        assert!(store.read_page(0, &mut out).unwrap_err().0.contains("CRC"));
        assert!(
            store.write_page(4, &[0u8; 10]).is_err(),
            "a short page is refused"
        );
    }
}
