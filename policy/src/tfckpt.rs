//! TensorFlow's checkpoint ("tensor bundle", V2), written and read: what rl_coach's saver
//! leaves in a DeepRacer model's `model/` folder as `N_Step-M.ckpt.index` and
//! `N_Step-M.ckpt.data-00000-of-00001`.
//!
//! **The data file** is the tensors' bytes back to back, little-endian, row-major in
//! TensorFlow's shape order, no padding (TensorFlow's default alignment of 1).
//!
//! **The index** is TensorFlow's copy of LevelDB's sorted table
//! (`core/lib/io/{table_builder,block_builder,format}.cc`): data blocks of entries (`varint32
//! shared, varint32 non_shared, varint32 value_len, key suffix, value`) with a restart point
//! every 16 entries and the restart offsets and their count at the block's end; after each
//! block a type byte (0 none, 1 Snappy) and the masked CRC-32C of the block and that byte; an
//! empty metaindex block; an index block (a restart at every entry) whose keys separate the
//! data blocks and whose values are their handles; a 48-byte footer of the two handles,
//! zero-padded, and the magic `0xdb4775248b80fb57`. Key `""` holds the `BundleHeaderProto`
//! (one shard, little-endian, version 1); every other key is a tensor's name and holds its
//! `BundleEntryProto` (dtype, shape, offset, size, masked CRC-32C of its bytes).
//!
//! Writing does what `BundleWriter` does, block for block and byte for byte: no compression,
//! blocks cut at 256 KiB, TensorFlow's shortest separators, tensors in name order. Reading
//! checks every trailer, restart array, handle, key order and checksum, and accepts Snappy
//! blocks as TensorFlow does; a file that is corrupt, truncated, cyclic (a handle pointing at
//! a block already read, or outside the blocks) or oversized is refused naming the file and
//! what was wrong. Writing goes through temporary files renamed into place: both files or
//! neither.

use crate::error::FileError;
use prost::Message;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// TensorFlow's DataType for `float`.
pub const DT_FLOAT: i32 = 1;
/// The table footer's magic number.
const MAGIC: u64 = 0xdb47_7524_8b80_fb57;
/// The footer's length: two handles padded to 40 bytes, then the magic.
const FOOTER: usize = 48;
/// TensorFlow's `block_size` for the bundle's table.
const BLOCK_SIZE: usize = 256 * 1024;
/// TensorFlow's `block_restart_interval` for data blocks.
const RESTART_INTERVAL: usize = 16;
/// The largest index file read.
pub const MAX_INDEX_BYTES: u64 = 64 << 20;
/// The largest data file read (a DEEPER network's three networks are well under this).
pub const MAX_DATA_BYTES: u64 = 4 << 30;
/// The most tensors an index may list.
pub const MAX_TENSORS: usize = 100_000;
/// The most dimensions a tensor may have.
const MAX_DIMS: usize = 16;
/// The longest key (a tensor's name) read.
const MAX_KEY: usize = 1 << 16;
/// The most bytes of keys and values a table's entries may add up to, rebuilt (each entry
/// repeats the prefix it shares with the one before).
const MAX_ENTRY_BYTES: usize = 256 << 20;

/// `BundleHeaderProto` (`core/protobuf/tensor_bundle.proto`).
#[derive(Clone, PartialEq, Message)]
struct BundleHeader {
    #[prost(int32, tag = "1")]
    num_shards: i32,
    /// 0 little-endian, 1 big-endian.
    #[prost(int32, tag = "2")]
    endianness: i32,
    #[prost(message, optional, tag = "3")]
    version: Option<crate::tfgraph::pb::VersionDef>,
}

/// `TensorSliceProto`: present only on partitioned tensors, which are refused.
#[derive(Clone, PartialEq, Message)]
struct TensorSlice {
    #[prost(bytes = "vec", repeated, tag = "1")]
    extent: Vec<Vec<u8>>,
}

/// `BundleEntryProto`.
#[derive(Clone, PartialEq, Message)]
struct BundleEntry {
    #[prost(int32, tag = "1")]
    dtype: i32,
    #[prost(message, optional, tag = "2")]
    shape: Option<crate::tfgraph::pb::TensorShapeProto>,
    #[prost(int32, tag = "3")]
    shard_id: i32,
    #[prost(int64, tag = "4")]
    offset: i64,
    #[prost(int64, tag = "5")]
    size: i64,
    #[prost(fixed32, tag = "6")]
    crc32c: u32,
    #[prost(message, repeated, tag = "7")]
    slices: Vec<TensorSlice>,
}

/// One tensor of a checkpoint.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// TensorFlow's DataType (1: float).
    pub dtype: i32,
    /// Its shape, TensorFlow's order.
    pub shape: Vec<usize>,
    /// Its bytes, little-endian.
    pub bytes: Vec<u8>,
}

impl Tensor {
    /// A float tensor.
    pub fn float(shape: Vec<usize>, values: &[f32]) -> Tensor {
        Tensor { dtype: DT_FLOAT, shape, bytes: values.iter().flat_map(|v| v.to_le_bytes()).collect() }
    }

    /// Its values, when it is a float tensor.
    pub fn floats(&self) -> Option<Vec<f32>> {
        (self.dtype == DT_FLOAT)
            .then(|| self.bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }
}

/// A checkpoint: tensors by name (sorted, as the index keeps them).
pub type Checkpoint = BTreeMap<String, Tensor>;

/// The index file of a checkpoint prefix (`X.index`).
pub fn index_path(prefix: &Path) -> PathBuf {
    with_suffix(prefix, ".index")
}

/// The one data file of a checkpoint prefix (`X.data-00000-of-00001`).
pub fn data_path(prefix: &Path) -> PathBuf {
    with_suffix(prefix, ".data-00000-of-00001")
}

fn with_suffix(prefix: &Path, suffix: &str) -> PathBuf {
    let mut s = prefix.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

/// The bytes of a DataType's element, for the types whose size is fixed.
fn element_size(dtype: i32) -> Option<usize> {
    // float, int32, uint32; double, int64, uint64, complex64; uint8, int8, bool; int16,
    // bfloat16, uint16, half.
    match dtype {
        1 | 3 | 22 => Some(4),
        2 | 8 | 9 | 23 => Some(8),
        4 | 6 | 10 => Some(1),
        5 | 14 | 17 | 19 => Some(2),
        _ => None,
    }
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// TensorFlow's (and LevelDB's) masked CRC-32C.
pub fn mask(crc: u32) -> u32 {
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

fn unmask(masked: u32) -> u32 {
    masked.wrapping_sub(0xa282_ead8).rotate_left(15)
}

/// LevelDB's block builder.
#[derive(Default)]
struct Block {
    buf: Vec<u8>,
    restarts: Vec<u32>,
    counter: usize,
    last: Vec<u8>,
    interval: usize,
}

impl Block {
    fn new(interval: usize) -> Block {
        Block { restarts: vec![0], interval, ..Default::default() }
    }

    fn add(&mut self, key: &[u8], value: &[u8]) {
        let shared = if self.counter < self.interval {
            self.last.iter().zip(key).take_while(|(a, b)| a == b).count()
        } else {
            self.restarts.push(self.buf.len() as u32);
            self.counter = 0;
            0
        };
        put_varint(&mut self.buf, shared as u64);
        put_varint(&mut self.buf, (key.len() - shared) as u64);
        put_varint(&mut self.buf, value.len() as u64);
        self.buf.extend_from_slice(&key[shared..]);
        self.buf.extend_from_slice(value);
        self.last = key.to_vec();
        self.counter += 1;
    }

    fn size_estimate(&self) -> usize {
        self.buf.len() + self.restarts.len() * 4 + 4
    }

    fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    fn finish(&mut self) -> Vec<u8> {
        let mut out = std::mem::take(&mut self.buf);
        for r in &self.restarts {
            out.extend_from_slice(&r.to_le_bytes());
        }
        out.extend_from_slice(&(self.restarts.len() as u32).to_le_bytes());
        *self = Block::new(self.interval);
        out
    }
}

/// The bytewise comparator's shortest key in `[start, limit)`.
fn shortest_separator(start: &[u8], limit: &[u8]) -> Vec<u8> {
    let n = start.iter().zip(limit).take_while(|(a, b)| a == b).count();
    if n < start.len().min(limit.len()) {
        let b = start[n];
        if b < 0xff && b + 1 < limit[n] {
            let mut s = start[..=n].to_vec();
            s[n] += 1;
            return s;
        }
    }
    start.to_vec()
}

/// The bytewise comparator's shortest key at or after `key`.
fn short_successor(key: &[u8]) -> Vec<u8> {
    match key.iter().position(|&b| b != 0xff) {
        Some(i) => {
            let mut s = key[..=i].to_vec();
            s[i] += 1;
            s
        }
        None => key.to_vec(),
    }
}

/// LevelDB's table builder, uncompressed, as TensorFlow's bundle writer uses it.
struct Table {
    out: Vec<u8>,
    data: Block,
    index: Block,
    last: Vec<u8>,
    pending: Option<(u64, u64)>,
}

impl Table {
    fn write_block(&mut self, contents: &[u8]) -> (u64, u64) {
        let handle = (self.out.len() as u64, contents.len() as u64);
        self.out.extend_from_slice(contents);
        let crc = crc32c::crc32c_append(crc32c::crc32c(contents), &[0]);
        self.out.push(0);
        self.out.extend_from_slice(&mask(crc).to_le_bytes());
        handle
    }

    fn add_index(&mut self, key: &[u8], handle: (u64, u64)) {
        let mut v = Vec::new();
        put_varint(&mut v, handle.0);
        put_varint(&mut v, handle.1);
        self.index.add(key, &v);
    }

    fn add(&mut self, key: &[u8], value: &[u8]) {
        if let Some(h) = self.pending.take() {
            let sep = shortest_separator(&self.last, key);
            self.add_index(&sep, h);
        }
        self.data.add(key, value);
        self.last = key.to_vec();
        if self.data.size_estimate() >= BLOCK_SIZE {
            self.flush();
        }
    }

    fn flush(&mut self) {
        if self.data.is_empty() {
            return;
        }
        let block = self.data.finish();
        self.pending = Some(self.write_block(&block));
    }

    fn finish(mut self) -> Vec<u8> {
        self.flush();
        let meta = Block::new(RESTART_INTERVAL).finish();
        let meta_handle = self.write_block(&meta);
        if let Some(h) = self.pending.take() {
            let succ = short_successor(&self.last);
            self.add_index(&succ, h);
        }
        let index = self.index.finish();
        let index_handle = self.write_block(&index);
        let mut footer = Vec::with_capacity(FOOTER);
        for h in [meta_handle, index_handle] {
            put_varint(&mut footer, h.0);
            put_varint(&mut footer, h.1);
        }
        footer.resize(FOOTER - 8, 0);
        footer.extend_from_slice(&(MAGIC as u32).to_le_bytes());
        footer.extend_from_slice(&((MAGIC >> 32) as u32).to_le_bytes());
        self.out.extend_from_slice(&footer);
        self.out
    }
}

/// The index's and the data file's bytes of a checkpoint of `tensors`.
pub fn encode(tensors: &Checkpoint) -> (Vec<u8>, Vec<u8>) {
    let mut table = Table {
        out: Vec::new(),
        data: Block::new(RESTART_INTERVAL),
        index: Block::new(1),
        last: vec![],
        pending: None,
    };
    let header = BundleHeader {
        num_shards: 1,
        endianness: 0,
        version: Some(crate::tfgraph::pb::VersionDef { producer: 1, min_consumer: 0, bad_consumers: vec![] }),
    };
    table.add(b"", &header.encode_to_vec());
    let mut data = Vec::new();
    for (name, t) in tensors {
        let entry = BundleEntry {
            dtype: t.dtype,
            shape: Some(crate::tfgraph::pb::TensorShapeProto {
                dim: t
                    .shape
                    .iter()
                    .map(|&size| crate::tfgraph::pb::tensor_shape_proto::Dim { size: size as i64, name: String::new() })
                    .collect(),
                unknown_rank: false,
            }),
            shard_id: 0,
            offset: data.len() as i64,
            size: t.bytes.len() as i64,
            crc32c: mask(crc32c::crc32c(&t.bytes)),
            slices: vec![],
        };
        data.extend_from_slice(&t.bytes);
        table.add(name.as_bytes(), &entry.encode_to_vec());
    }
    (table.finish(), data)
}

/// Write the checkpoint at `prefix` (`prefix.index` and `prefix.data-00000-of-00001`), both
/// files or neither.
pub fn write(prefix: &Path, tensors: &Checkpoint) -> Result<(), FileError> {
    let (index, data) = encode(tensors);
    let (ip, dp) = (index_path(prefix), data_path(prefix));
    let tmp = |p: &Path| with_suffix(p, ".tmp");
    let result = std::fs::write(tmp(&dp), &data)
        .map_err(FileError::io_at(&dp))
        .and_then(|()| std::fs::write(tmp(&ip), &index).map_err(FileError::io_at(&ip)))
        .and_then(|()| std::fs::rename(tmp(&dp), &dp).map_err(FileError::io_at(&dp)))
        .and_then(|()| std::fs::rename(tmp(&ip), &ip).map_err(FileError::io_at(&ip)));
    if result.is_err() {
        let _ = std::fs::remove_file(tmp(&dp));
        let _ = std::fs::remove_file(tmp(&ip));
    }
    result
}

/// Read the checkpoint at `prefix`.
pub fn read(prefix: &Path) -> Result<Checkpoint, FileError> {
    let (ip, dp) = (index_path(prefix), data_path(prefix));
    let index = read_bounded(&ip, MAX_INDEX_BYTES)?;
    let data = read_bounded(&dp, MAX_DATA_BYTES)?;
    decode(&index, &data, &ip.display().to_string(), &dp.display().to_string())
}

fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>, FileError> {
    let len = std::fs::metadata(path).map_err(FileError::io_at(path))?.len();
    if len > max {
        return Err(FileError::invalid(path.display().to_string(), format!("{len} bytes, over the {max} read")));
    }
    std::fs::read(path).map_err(FileError::io_at(path))
}

/// A reader over bytes that names what it reads in its errors.
struct Cursor<'a> {
    buf: &'a [u8],
    at: usize,
}

impl Cursor<'_> {
    fn varint(&mut self, what: &str) -> Result<u64, String> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let Some(&b) = self.buf.get(self.at) else { return Err(format!("{what}: truncated varint")) };
            self.at += 1;
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(format!("{what}: varint longer than 10 bytes"))
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&[u8], String> {
        let end =
            self.at.checked_add(n).filter(|&e| e <= self.buf.len()).ok_or_else(|| format!("{what}: truncated"))?;
        let s = &self.buf[self.at..end];
        self.at = end;
        Ok(s)
    }
}

/// A block's contents, checked against its trailer and decompressed.
fn block<'a>(
    file: &'a [u8],
    handle: (u64, u64),
    limit: usize,
    what: &str,
) -> Result<std::borrow::Cow<'a, [u8]>, String> {
    let (off, size) = handle;
    let end = off.checked_add(size).and_then(|e| e.checked_add(5));
    let Some(end) = end.filter(|&e| e <= limit as u64) else {
        return Err(format!("{what}: block at {off} of {size} bytes lies outside the table's blocks"));
    };
    let (off, end) = (off as usize, end as usize);
    let contents = &file[off..end - 5];
    let kind = file[end - 5];
    let stored = u32::from_le_bytes(file[end - 4..end].try_into().expect("4 bytes"));
    let crc = crc32c::crc32c_append(crc32c::crc32c(contents), &[kind]);
    if unmask(stored) != crc {
        return Err(format!("{what}: block at {off}: checksum mismatch (corrupt)"));
    }
    match kind {
        0 => Ok(std::borrow::Cow::Borrowed(contents)),
        1 => {
            let n = snap::raw::decompress_len(contents).map_err(|e| format!("{what}: block at {off}: {e}"))?;
            if n as u64 > MAX_INDEX_BYTES {
                return Err(format!("{what}: block at {off} unpacks to {n} bytes, over the {MAX_INDEX_BYTES} read"));
            }
            snap::raw::Decoder::new()
                .decompress_vec(contents)
                .map(std::borrow::Cow::Owned)
                .map_err(|e| format!("{what}: block at {off}: Snappy: {e}"))
        }
        k => Err(format!("{what}: block at {off}: compression type {k} (TensorFlow knows 0, none, and 1, Snappy)")),
    }
}

/// A block's entries, keys rebuilt from their shared prefixes.
/// A block's entries: (key, value).
type Entries = Vec<(Vec<u8>, Vec<u8>)>;

fn entries(b: &[u8], what: &str, budget: &mut usize) -> Result<Entries, String> {
    if b.len() < 4 {
        return Err(format!("{what}: block of {} bytes has no restart count", b.len()));
    }
    let n = u32::from_le_bytes(b[b.len() - 4..].try_into().expect("4 bytes")) as usize;
    let restarts_at = n
        .checked_mul(4)
        .and_then(|r| (b.len() - 4).checked_sub(r))
        .ok_or_else(|| format!("{what}: {n} restart points do not fit a block of {} bytes", b.len()))?;
    if n == 0 && restarts_at > 0 {
        return Err(format!("{what}: a block with entries and no restart point"));
    }
    let restarts: Vec<usize> = b[restarts_at..b.len() - 4]
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes(c.try_into().expect("4 bytes")) as usize)
        .collect();
    let mut c = Cursor { buf: &b[..restarts_at], at: 0 };
    let mut out: Entries = Vec::new();
    let mut key: Vec<u8> = Vec::new();
    let mut next_restart = 0;
    while c.at < restarts_at {
        let at = c.at;
        let shared = c.varint(what)? as usize;
        let non_shared = c.varint(what)? as usize;
        let value_len = c.varint(what)? as usize;
        let is_restart = restarts.get(next_restart) == Some(&at);
        if is_restart {
            next_restart += 1;
        }
        if (is_restart || out.is_empty()) && shared != 0 {
            return Err(format!("{what}: entry at {at} shares {shared} bytes at a restart point"));
        }
        if shared > key.len() {
            return Err(format!("{what}: entry at {at} shares {shared} bytes of a {}-byte key", key.len()));
        }
        if shared + non_shared > MAX_KEY {
            return Err(format!("{what}: entry at {at}: a key of {} bytes (over {MAX_KEY})", shared + non_shared));
        }
        *budget = budget
            .checked_sub(shared + non_shared + value_len)
            .ok_or_else(|| format!("{what}: entries over {MAX_ENTRY_BYTES} bytes of keys and values"))?;
        key.truncate(shared);
        key.extend_from_slice(c.take(non_shared, what)?);
        let value = c.take(value_len, what)?.to_vec();
        if let Some((prev, _)) = out.last()
            && prev.as_slice() >= key.as_slice()
        {
            return Err(format!("{what}: keys out of order at {}", String::from_utf8_lossy(&key)));
        }
        out.push((key.clone(), value));
        if out.len() > MAX_TENSORS + 1 {
            return Err(format!("{what}: over {MAX_TENSORS} entries"));
        }
    }
    if next_restart != restarts.len() {
        return Err(format!("{what}: {} restart points, {next_restart} of them at entries", restarts.len()));
    }
    Ok(out)
}

/// [`read`] of the two files' bytes; `index_name` and `data_name` name them in errors.
pub fn decode(index: &[u8], data: &[u8], index_name: &str, data_name: &str) -> Result<Checkpoint, FileError> {
    let bad = |m: String| FileError::invalid(index_name, m);
    if index.len() < FOOTER {
        return Err(bad(format!(
            "{} bytes: too short for a TensorFlow index (its footer alone is {FOOTER})",
            index.len()
        )));
    }
    let footer = &index[index.len() - FOOTER..];
    let magic = u64::from(u32::from_le_bytes(footer[40..44].try_into().expect("4")))
        | (u64::from(u32::from_le_bytes(footer[44..48].try_into().expect("4"))) << 32);
    if magic != MAGIC {
        return Err(bad(format!("footer magic {magic:#018x}, not a TensorFlow table's ({MAGIC:#018x})")));
    }
    let mut c = Cursor { buf: &footer[..40], at: 0 };
    let meta = (c.varint("footer").map_err(&bad)?, c.varint("footer").map_err(&bad)?);
    let ih = (c.varint("footer").map_err(&bad)?, c.varint("footer").map_err(&bad)?);
    let limit = index.len() - FOOTER;
    // The metaindex is checked (TensorFlow reads nothing from it).
    block(index, meta, limit, "metaindex block").map_err(&bad)?;
    let ib = block(index, ih, limit, "index block").map_err(&bad)?;
    let mut budget = MAX_ENTRY_BYTES;
    let handles = entries(&ib, "index block", &mut budget).map_err(&bad)?;
    let mut seen: Vec<(u64, u64)> = Vec::new();
    let mut all: Entries = Vec::new();
    for (sep, v) in &handles {
        let mut hc = Cursor { buf: v, at: 0 };
        let h = (hc.varint("index entry").map_err(&bad)?, hc.varint("index entry").map_err(&bad)?);
        // Each data block once, each after the one before: no cycles, no overlaps.
        if let Some(&(po, ps)) = seen.last()
            && h.0 < po + ps + 5
        {
            return Err(bad(format!(
                "index entry {}: block at {} overlaps or repeats an earlier one",
                String::from_utf8_lossy(sep),
                h.0
            )));
        }
        if h.0.saturating_add(h.1).saturating_add(5) > meta.0 {
            return Err(bad(format!(
                "index entry {}: block at {} runs into the metaindex",
                String::from_utf8_lossy(sep),
                h.0
            )));
        }
        seen.push(h);
        let b = block(index, h, limit, "data block").map_err(&bad)?;
        let es = entries(&b, "data block", &mut budget).map_err(&bad)?;
        if let (Some((last, _)), Some((first, _))) = (all.last(), es.first())
            && last >= first
        {
            return Err(bad(format!("keys out of order between blocks at {}", String::from_utf8_lossy(first))));
        }
        if let Some((last, _)) = es.last()
            && last.as_slice() > sep.as_slice()
        {
            return Err(bad(format!("index key {} is below its block's last key", String::from_utf8_lossy(sep))));
        }
        all.extend(es);
        if all.len() > MAX_TENSORS + 1 {
            return Err(bad(format!("over {MAX_TENSORS} tensors")));
        }
    }
    let mut it = all.into_iter();
    let Some((k, header)) = it.next().filter(|(k, _)| k.is_empty()) else {
        return Err(bad("no bundle header (the empty key): not a TensorFlow checkpoint index".into()));
    };
    debug_assert!(k.is_empty());
    let header = BundleHeader::decode(header.as_slice()).map_err(|e| bad(format!("bundle header: {e}")))?;
    if header.num_shards != 1 {
        return Err(bad(format!(
            "{} data shards: a checkpoint of one data file (.data-00000-of-00001) is read, as rl_coach writes",
            header.num_shards
        )));
    }
    if header.endianness != 0 {
        return Err(bad("a big-endian checkpoint: its tensors' bytes are not this machine's order".into()));
    }
    if let Some(v) = &header.version
        && (v.producer < 0 || v.min_consumer > 1 || v.bad_consumers.contains(&1))
    {
        return Err(bad(format!("bundle version {v:?}: this reader is TensorFlow's version 1 consumer")));
    }
    let mut out = Checkpoint::new();
    // The tensors' bytes, all told, fit the data file: no two share a range.
    let mut left = data.len() as u64;
    for (key, value) in it {
        let name = String::from_utf8(key).map_err(|_| bad("a tensor name is not UTF-8".into()))?;
        let e = BundleEntry::decode(value.as_slice()).map_err(|err| bad(format!("tensor {name}: entry: {err}")))?;
        if !e.slices.is_empty() {
            return Err(bad(format!("tensor {name} is partitioned into slices; rl_coach saves whole tensors")));
        }
        if e.shard_id != 0 {
            return Err(bad(format!("tensor {name} is in shard {}; the checkpoint has one", e.shard_id)));
        }
        let dims = e.shape.map(|s| s.dim).unwrap_or_default();
        if dims.len() > MAX_DIMS || dims.iter().any(|d| d.size < 0) {
            return Err(bad(format!(
                "tensor {name}: shape {:?} is not a tensor's",
                dims.iter().map(|d| d.size).collect::<Vec<_>>()
            )));
        }
        let shape: Vec<usize> = dims.iter().map(|d| d.size as usize).collect();
        let count = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        let (off, size) = (e.offset, e.size);
        if off < 0 || size < 0 || (off as u64).saturating_add(size as u64) > data.len() as u64 {
            return Err(FileError::invalid(
                data_name,
                format!(
                    "tensor {name}: bytes {off}..{} lie outside the file's {}",
                    off.saturating_add(size),
                    data.len()
                ),
            ));
        }
        if let Some(el) = element_size(e.dtype) {
            let want = count.and_then(|n| n.checked_mul(el));
            if want != Some(size as usize) {
                return Err(bad(format!("tensor {name}: {size} bytes for shape {shape:?} of dtype {}", e.dtype)));
            }
        }
        left = left.checked_sub(size as u64).ok_or_else(|| {
            FileError::invalid(
                data_name,
                format!("tensor {name}: the tensors' ranges overlap (more bytes than the file's {})", data.len()),
            )
        })?;
        let bytes = &data[off as usize..(off + size) as usize];
        if mask(crc32c::crc32c(bytes)) != e.crc32c {
            return Err(FileError::invalid(data_name, format!("tensor {name}: checksum mismatch (corrupt)")));
        }
        out.insert(name, Tensor { dtype: e.dtype, shape, bytes: bytes.to_vec() });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        let mut c = Checkpoint::new();
        c.insert("a/kernel".into(), Tensor::float(vec![2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
        c.insert("a/bias".into(), Tensor::float(vec![3], &[0.5, -0.5, 0.25]));
        c.insert("scalar".into(), Tensor::float(vec![], &[1.0]));
        c
    }

    /// Issue 53: a checkpoint comes back as written, its header as TensorFlow writes it.
    #[test]
    fn a_checkpoint_comes_back_as_written() {
        let c = sample();
        let (index, data) = encode(&c);
        assert_eq!(data.len(), 4 * 10);
        // The header's value as BundleWriter writes it: one shard, little-endian, version 1.
        let header = [0x08, 0x01, 0x1a, 0x02, 0x08, 0x01];
        assert!(index.windows(6).any(|w| w == header));
        assert_eq!(&index[index.len() - 8..], &[0x57, 0xfb, 0x80, 0x8b, 0x24, 0x75, 0x47, 0xdb]);
        assert_eq!(decode(&index, &data, "x.index", "x.data").unwrap(), c);
        // Data in name order, as TensorFlow's saver writes it.
        assert_eq!(&data[..4], &0.5f32.to_le_bytes());
    }

    /// Issue 53: many tensors span several blocks with restart points and separators, and
    /// come back.
    #[test]
    fn many_tensors_span_blocks_and_come_back() {
        let mut c = Checkpoint::new();
        for i in 0..12_000 {
            c.insert(
                format!("main_level/agent/main/online/network_{}/layer_{i:05}/kernel", i % 3),
                Tensor::float(vec![40], &[i as f32; 40]),
            );
        }
        let (index, data) = encode(&c);
        assert!(index.len() > BLOCK_SIZE, "several data blocks: {}", index.len());
        assert_eq!(decode(&index, &data, "i", "d").unwrap(), c);
    }

    /// Issue 53: separators and successors are the bytewise comparator's.
    #[test]
    fn separators_are_the_bytewise_comparators() {
        for (a, b, want) in [
            (&b"abc"[..], &b"abz"[..], &b"abd"[..]),
            (b"abc", b"abd", b"abc"),
            (b"ab", b"abc", b"ab"),
            (b"a\xff", b"b", b"a\xff"),
        ] {
            assert_eq!(shortest_separator(a, b), want, "{a:?} {b:?}");
        }
        assert_eq!(short_successor(b"abc"), b"b");
        assert_eq!(short_successor(b"\xff\xffx"), b"\xff\xffy");
    }

    /// Issue 53: a corrupt, truncated or tampered checkpoint is refused naming the file and
    /// what was wrong.
    #[test]
    fn damaged_checkpoints_are_refused_naming_the_file() {
        let (index, data) = encode(&sample());
        let flip = |i: usize| {
            let mut x = index.clone();
            x[i] ^= 0x40;
            x
        };
        let cases: Vec<(Vec<u8>, Vec<u8>, &str)> = vec![
            (index[..20].to_vec(), data.clone(), "x.index: 20 bytes: too short"),
            (index[..index.len() - 1].to_vec(), data.clone(), "x.index: footer magic"),
            (flip(3), data.clone(), "x.index: data block: block at 0: checksum mismatch"),
            (index.clone(), data[..30].to_vec(), "x.data: tensor a/kernel: bytes 12..36 lie outside"),
            (
                index.clone(),
                {
                    let mut d = data.clone();
                    d[13] ^= 1;
                    d
                },
                "x.data: tensor a/kernel: checksum mismatch",
            ),
        ];
        for (i, d, want) in cases {
            let e = decode(&i, &d, "x.index", "x.data").unwrap_err().to_string();
            assert!(e.starts_with(want), "{want}: {e}");
        }
        // A data block handle pointing back at the index block (a cycle) is refused.
        let mut c = Cursor { buf: &index[index.len() - FOOTER..], at: 0 };
        let _meta = (c.varint("").unwrap(), c.varint("").unwrap());
        let (io, is) = (c.varint("").unwrap(), c.varint("").unwrap());
        let mut t = Table {
            out: index[..io as usize].to_vec(),
            data: Block::new(16),
            index: Block::new(1),
            last: vec![],
            pending: None,
        };
        t.add_index(b"\xff", (io, is));
        let ib = t.index.finish();
        let new_ih = t.write_block(&ib);
        let mut looped = t.out;
        let mut footer = Vec::new();
        for h in [_meta, new_ih] {
            put_varint(&mut footer, h.0);
            put_varint(&mut footer, h.1);
        }
        footer.resize(40, 0);
        footer.extend_from_slice(&index[index.len() - 8..]);
        looped.extend_from_slice(&footer);
        let e = decode(&looped, &data, "x.index", "x.data").unwrap_err().to_string();
        assert!(e.contains("runs into the metaindex") || e.contains("overlaps"), "{e}");
    }

    /// Issue 53: entries that share one long key many times over, and tensors that share one
    /// range of the data file, are refused before they cost memory.
    #[test]
    fn amplifying_checkpoints_are_refused() {
        let mut t = Table { out: vec![], data: Block::new(1 << 30), index: Block::new(1), last: vec![], pending: None };
        let long = vec![b'a'; 60_000];
        t.add(b"", b"");
        for i in 0..6000u32 {
            let mut k = long.clone();
            k.extend_from_slice(&i.to_be_bytes());
            t.add(&k, b"");
        }
        let e = decode(&t.finish(), b"", "x.index", "x.data").unwrap_err().to_string();
        assert!(e.contains("entries over"), "{e}");
        // Two entries over the same 16 bytes.
        let data = [0u8; 16];
        let mut t = Table { out: vec![], data: Block::new(16), index: Block::new(1), last: vec![], pending: None };
        t.add(b"", &BundleHeader { num_shards: 1, ..Default::default() }.encode_to_vec());
        for name in [b"a", b"b"] {
            let e = BundleEntry {
                dtype: DT_FLOAT,
                shape: Some(crate::tfgraph::pb::TensorShapeProto {
                    dim: vec![crate::tfgraph::pb::tensor_shape_proto::Dim { size: 4, name: String::new() }],
                    unknown_rank: false,
                }),
                size: 16,
                crc32c: mask(crc32c::crc32c(&data)),
                ..Default::default()
            };
            t.add(name, &e.encode_to_vec());
        }
        let e = decode(&t.finish(), &data, "x.index", "x.data").unwrap_err().to_string();
        assert!(e.starts_with("x.data: tensor b: the tensors' ranges overlap"), "{e}");
    }

    /// Issue 53: written files are both there or neither, and read back.
    #[test]
    fn written_files_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let prefix = dir.path().join("3_Step-120.ckpt");
        write(&prefix, &sample()).unwrap();
        assert!(index_path(&prefix).ends_with("3_Step-120.ckpt.index"));
        assert_eq!(read(&prefix).unwrap(), sample());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
        let e = read(&dir.path().join("nothing.ckpt")).unwrap_err().to_string();
        assert!(e.contains("nothing.ckpt.index"), "{e}");
    }
}
