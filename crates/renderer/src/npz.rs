//! A small, strict reader and writer for NumPy `.npy` arrays inside `.npz` (zip) files:
//! little-endian numeric dtypes and unicode scalars only. Object arrays are refused
//! outright; nothing here can execute code. This file holds the zip container; `npz/npy.rs`
//! the `.npy` arrays in it.
//!
//! The reader trusts nothing it has not checked: the zip's declared entry sizes are held against
//! the file's real size and [`MAX_ENTRY_BYTES`] before an entry is opened, and a `.npy` header's
//! shape and dtype against the entry's size before its data is read, so a hostile size claim is an
//! error, never an allocation. `lp3d.render.npz_reader` is the Python twin (same grammar, same limits).

use std::io::{Read, Seek, Write};

mod npy;

use npy::io_message;
pub use npy::*;

/// Largest accepted `.npy` entry inside an `.npz` (the largest legal array, 2048 x 2048 float32
/// planes, is 1.5 GiB).
pub const MAX_ENTRY_BYTES: u64 = 2 << 30;
/// Most entries an `.npz` may list (a triplane file has at most 13 keys).
pub const MAX_ENTRIES: usize = 32;
/// An `.npz` archive whose container has been checked: at most [`MAX_ENTRIES`] entries, no name
/// twice, every entry stored (not compressed), unencrypted, and declaring a size within
/// [`MAX_ENTRY_BYTES`] and within the file. Entries are read by key, header first.
pub struct NpzReader<R: Read + Seek> {
    zip: zip::ZipArchive<R>,
    /// (key, index in the zip, size in bytes), in archive order.
    entries: Vec<(String, usize, u64)>,
}

/// An error in an `.npz`: (key, message); the key is empty for the archive as a whole.
pub type NpzError = (String, String);

impl<R: Read + Seek> NpzReader<R> {
    /// Checks the container of an archive `file_bytes` long (the real size, from the file system).
    pub fn new(reader: R, file_bytes: u64) -> Result<Self, NpzError> {
        let whole = |m: String| (String::new(), m);
        let zip =
            zip::ZipArchive::new(reader).map_err(|e| whole(format!("not a valid .npz (zip) file: {e}")))?;
        if zip.has_duplicate_names() {
            return Err(whole("the archive lists an entry name twice".into()));
        }
        if zip.len() > MAX_ENTRIES {
            return Err(whole(format!("{} entries, more than the cap of {MAX_ENTRIES}", zip.len())));
        }
        let mut entries = Vec::with_capacity(zip.len());
        for i in 0..zip.len() {
            let e = zip.by_index_data(i).map_err(|e| whole(format!("corrupt entry {i}: {e}")))?;
            let name = e.name().map_err(|e| whole(format!("bad entry name: {e}")))?;
            let key = name.strip_suffix(".npy").unwrap_or(&name).to_string();
            let fail = |m: String| Err((key.clone(), m));
            if e.encrypted() {
                return fail("encrypted entries are not supported".into());
            }
            if e.compression() != zip::CompressionMethod::Stored {
                return fail(format!(
                    "entry is compressed ({}); triplane files are uncompressed (numpy.savez, not \
                     savez_compressed)",
                    e.compression()
                ));
            }
            let (size, stored) = (e.size(), e.compressed_size());
            if size != stored {
                return fail(format!(
                    "stored entry declares {stored} bytes in the file but {size} bytes of data"
                ));
            }
            if size > MAX_ENTRY_BYTES {
                return fail(format!("entry declares {size} bytes, more than the cap of {MAX_ENTRY_BYTES}"));
            }
            // Its local header (30 bytes at least) and data lie inside the file.
            if e.header_start().saturating_add(30).saturating_add(size) > file_bytes {
                return fail(format!(
                    "entry declares {size} bytes at offset {}, past the end of the {file_bytes}-byte file",
                    e.header_start()
                ));
            }
            entries.push((key, i, size));
        }
        Ok(NpzReader { zip, entries })
    }

    /// Keys (entry names less `.npy`), in archive order.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.entries.iter().map(|(k, _, _)| k.as_str())
    }

    fn entry(&mut self, key: &str) -> Result<(zip::read::ZipFile<'_, R>, u64), String> {
        let (_, index, size) = self.entries.iter().find(|(k, _, _)| k == key).ok_or("no such entry")?;
        let (index, size) = (*index, *size);
        let file = self.zip.by_index(index).map_err(|e| format!("corrupt entry: {e}"))?;
        Ok((file, size))
    }

    /// The entry's `.npy` header, checked against the entry's size; no data is read.
    pub fn header(&mut self, key: &str) -> Result<NpyHeader, String> {
        let (mut file, size) = self.entry(key)?;
        read_npy_header(&mut file, size)
    }

    /// The entry's data, as `header` (from [`NpzReader::header`]) describes it; CRC-checked.
    pub fn read(&mut self, key: &str, header: &NpyHeader) -> Result<NpyData, String> {
        let (mut file, _) = self.entry(key)?;
        let mut skip = vec![0u8; header.data_offset];
        file.read_exact(&mut skip).map_err(io_message)?;
        read_npy_data(&mut file, header)
    }
}

/// Writes arrays as an uncompressed `.npz` (what `numpy.savez` writes).
pub fn write_npz<W: Write + Seek>(writer: W, arrays: &[(&str, NpyArray)]) -> std::io::Result<()> {
    let mut zip = zip::ZipWriter::new(writer);
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(true);
    for (key, array) in arrays {
        zip.start_file(format!("{key}.npy"), options).map_err(std::io::Error::other)?;
        zip.write_all(&write_npy(array))?;
    }
    zip.finish().map_err(std::io::Error::other)?;
    Ok(())
}
