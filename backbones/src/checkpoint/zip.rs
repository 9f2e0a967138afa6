//! The part of the ZIP format that PyTorch's checkpoints use: a central directory (with ZIP64
//! extensions for large files) listing entries that are stored without compression. An entry
//! is returned as the byte range of its data inside the file.

use std::collections::BTreeMap;
use std::ops::Range;

const EOCD_SIG: u32 = 0x0605_4b50;
const ZIP64_LOCATOR_SIG: u32 = 0x0706_4b50;
const ZIP64_EOCD_SIG: u32 = 0x0606_4b50;
const CENTRAL_SIG: u32 = 0x0201_4b50;
const LOCAL_SIG: u32 = 0x0403_4b50;
/// Fixed part of the end-of-central-directory record.
const EOCD_LEN: usize = 22;

/// Little-endian field reads with bounds checks.
struct Reader<'a> {
    bytes: &'a [u8],
}

impl Reader<'_> {
    fn slice(&self, at: usize, len: usize) -> Result<&[u8], String> {
        at.checked_add(len)
            .and_then(|end| self.bytes.get(at..end))
            .ok_or_else(|| format!("record at byte {at} runs past the end of the file (truncated?)"))
    }
    fn u16(&self, at: usize) -> Result<u16, String> {
        let b = self.slice(at, 2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&self, at: usize) -> Result<u32, String> {
        let b = self.slice(at, 4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&self, at: usize) -> Result<u64, String> {
        let b = self.slice(at, 8)?;
        Ok(u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
    }
}

fn to_usize(v: u64, what: &str) -> Result<usize, String> {
    usize::try_from(v).map_err(|_| format!("{what} {v} does not fit in memory"))
}

/// Entry name → byte range of its (stored, uncompressed) data.
pub fn read_entries(bytes: &[u8]) -> Result<BTreeMap<String, Range<usize>>, String> {
    let r = Reader { bytes };
    // The end record sits in the last 22 + 65535 (comment) bytes.
    let lowest = bytes.len().saturating_sub(EOCD_LEN + u16::MAX as usize);
    let eocd = (lowest..=bytes.len().saturating_sub(EOCD_LEN))
        .rev()
        .find(|&at| bytes.len() >= EOCD_LEN && r.u32(at).ok() == Some(EOCD_SIG))
        .ok_or("no ZIP end-of-directory record: the file is truncated (an interrupted download?) or not a zip")?;
    let mut count = r.u16(eocd + 10)? as u64;
    let mut dir_size = r.u32(eocd + 12)? as u64;
    let mut dir_offset = r.u32(eocd + 16)? as u64;
    if count == 0xFFFF || dir_size == 0xFFFF_FFFF || dir_offset == 0xFFFF_FFFF {
        let locator = eocd.checked_sub(20).ok_or("ZIP64 locator missing")?;
        if r.u32(locator)? != ZIP64_LOCATOR_SIG {
            return Err("ZIP64 end-of-directory locator missing".into());
        }
        let at = to_usize(r.u64(locator + 8)?, "ZIP64 record offset")?;
        if r.u32(at)? != ZIP64_EOCD_SIG {
            return Err("ZIP64 end-of-directory record missing".into());
        }
        count = r.u64(at + 32)?;
        dir_size = r.u64(at + 40)?;
        dir_offset = r.u64(at + 48)?;
    }
    let dir_offset = to_usize(dir_offset, "directory offset")?;
    r.slice(dir_offset, to_usize(dir_size, "directory size")?)?;

    let mut entries = BTreeMap::new();
    let mut at = dir_offset;
    for _ in 0..count {
        if r.u32(at)? != CENTRAL_SIG {
            return Err(format!("bad central-directory entry at byte {at} (corrupt file)"));
        }
        let method = r.u16(at + 10)?;
        let mut compressed = r.u32(at + 20)? as u64;
        let mut size = r.u32(at + 24)? as u64;
        let name_len = r.u16(at + 28)? as usize;
        let extra_len = r.u16(at + 30)? as usize;
        let comment_len = r.u16(at + 32)? as usize;
        let mut local = r.u32(at + 42)? as u64;
        let name = String::from_utf8_lossy(r.slice(at + 46, name_len)?).into_owned();
        // ZIP64 extra field: the 64-bit values of the fields saturated above, in this order.
        let mut extra = at + 46 + name_len;
        let extra_end = extra + extra_len;
        while extra + 4 <= extra_end {
            let (id, len) = (r.u16(extra)?, r.u16(extra + 2)? as usize);
            if id == 0x0001 {
                let mut p = extra + 4;
                for field in [&mut size, &mut compressed, &mut local] {
                    if *field == 0xFFFF_FFFF && p + 8 <= extra + 4 + len {
                        *field = r.u64(p)?;
                        p += 8;
                    }
                }
            }
            extra += 4 + len;
        }
        if method != 0 {
            return Err(format!(
                "entry `{name}` is compressed (method {method}); PyTorch writes checkpoints uncompressed — \
                 use the file as `torch.save` wrote it rather than a re-zipped copy"
            ));
        }
        if compressed != size {
            return Err(format!(
                "entry `{name}`: stored size {compressed} differs from its size {size} (corrupt file)"
            ));
        }
        let local = to_usize(local, "entry offset")?;
        if r.u32(local)? != LOCAL_SIG {
            return Err(format!("entry `{name}`: bad local header at byte {local} (corrupt file)"));
        }
        let start = local + 30 + r.u16(local + 26)? as usize + r.u16(local + 28)? as usize;
        let len = to_usize(size, "entry size")?;
        r.slice(start, len)
            .map_err(|_| format!("entry `{name}` runs past the end of the file (truncated download?)"))?;
        entries.insert(name, start..start + len);
        at = extra_end + comment_len;
    }
    Ok(entries)
}
