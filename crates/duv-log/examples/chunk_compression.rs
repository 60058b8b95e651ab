//! Ratio and writer time of the MCAP chunk compressions on a real log:
//! `cargo run -p duv-log --example chunk_compression -- RUN/log [REPEATS]` (the dev profile
//! builds dependencies, libzstd and lz4_flex included, at opt-level 3).
//! Every message of the log's segments is written again through [`ChunkedWriter`] (512 KiB
//! chunks, as the log writer uses) with each compression, all topics together and each topic
//! on its own; the time is the writer's (encoding excluded), the median of REPEATS (3).

use duv_log::chunked::{ChunkCompression, ChunkedWriter, WriterBuffers};
use duv_log::reader::{read_segment, ReadLimits};
use std::collections::BTreeMap;
use std::time::Instant;

fn write_all(messages: &[(u16, u64, &[u8])], channels: &BTreeMap<u16, String>, kind: ChunkCompression, out: Vec<u8>, buf: WriterBuffers) -> (Vec<u8>, WriterBuffers, f64) {
    let t0 = Instant::now();
    let mut w = ChunkedWriter::new(out, "bench", 512 << 10, buf).unwrap();
    w.set_compression(kind);
    for (&id, topic) in channels {
        w.add_channel(id, 0, topic, "bytes", &BTreeMap::new()).unwrap();
    }
    for (i, &(id, t, data)) in messages.iter().enumerate() {
        w.write_message(id, i as u32, t, t, data).unwrap();
    }
    let (out, buf) = w.finish().unwrap();
    (out, buf, t0.elapsed().as_secs_f64())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = std::path::Path::new(args.get(1).expect("usage: chunk_compression LOG_DIR [REPEATS]"));
    let repeats: usize = args.get(2).and_then(|r| r.parse().ok()).unwrap_or(3);
    let mut owned: Vec<(u16, u64, Vec<u8>)> = Vec::new();
    let mut channels = BTreeMap::new();
    for (_, path) in duv_log::list_segments(dir).unwrap() {
        read_segment(&path, ReadLimits { max_record_bytes: 256 << 20 }, |m| {
            channels.insert(m.channel.id, m.channel.topic.clone());
            owned.push((m.channel.id, m.log_time_ns, m.data.to_vec()));
        })
        .unwrap();
    }
    let messages: Vec<(u16, u64, &[u8])> = owned.iter().map(|(c, t, d)| (*c, *t, d.as_slice())).collect();
    let raw: usize = messages.iter().map(|m| m.2.len()).sum();
    println!("{}: {} messages, {:.1} MB of message bytes", dir.display(), messages.len(), raw as f64 / 1e6);
    let kinds = [ChunkCompression::None, ChunkCompression::Zstd, ChunkCompression::Lz4];
    let mut buf = WriterBuffers::default();
    let mut out = Vec::with_capacity(raw + (raw >> 3) + (1 << 20));
    println!("{:<22} {:>12} {:>12} {:>12} {:>12} {:>12} {:>10} {:>10}", "topic", "MB", "zstd MB", "lz4 MB", "zstd ratio", "lz4 ratio", "zstd ms", "lz4 ms");
    let mut rows: Vec<(String, Vec<u16>)> = channels.iter().map(|(id, t)| (t.clone(), vec![*id])).collect();
    rows.push(("all topics".into(), channels.keys().copied().collect()));
    for (name, ids) in rows {
        let subset: Vec<(u16, u64, &[u8])> = messages.iter().filter(|m| ids.contains(&m.0)).copied().collect();
        let chans: BTreeMap<u16, String> = channels.iter().filter(|(id, _)| ids.contains(id)).map(|(a, b)| (*a, b.clone())).collect();
        let mut sizes = Vec::new();
        let mut times = Vec::new();
        for kind in kinds {
            let mut ts = Vec::new();
            let mut size = 0;
            for _ in 0..repeats.max(1) {
                out.clear();
                let (o, b, s) = write_all(&subset, &chans, kind, std::mem::take(&mut out), std::mem::take(&mut buf));
                size = o.len();
                out = o;
                buf = b;
                ts.push(s);
            }
            ts.sort_by(f64::total_cmp);
            sizes.push(size as f64);
            times.push(ts[ts.len() / 2] * 1e3);
        }
        println!(
            "{:<22} {:>12.2} {:>12.2} {:>12.2} {:>12.3} {:>12.3} {:>10.1} {:>10.1}",
            name,
            sizes[0] / 1e6,
            sizes[1] / 1e6,
            sizes[2] / 1e6,
            sizes[1] / sizes[0],
            sizes[2] / sizes[0],
            times[1] - times[0],
            times[2] - times[0]
        );
    }
    println!("(ratio: compressed file / uncompressed file; ms: writer time over the uncompressed writer's, median of {repeats})");
}
