//! The object store as the NATS backend writes it, in process: blobs of every size class
//! (empty, one byte, exactly one chunk, one chunk and a byte, three chunks) read back
//! byte for byte; a blob written again keeps one chunk set; a delete leaves nothing.

use super::*;
use willow_service::jobs::nats::{connect, NatsOptions};
use willow_service::jobs::ports::BlobKey;
use willow_service::jobs::{Config, JobId};

/// The object store's chunk size (the clients' default, which the backend keeps).
const CHUNK: usize = 128 * 1024;

/// `len` bytes that differ from chunk to chunk (a chunk read twice or out of order shows).
fn pattern(len: usize, seed: u8) -> bytes::Bytes {
    (0..len)
        .map(|i| {
            (i as u8)
                .wrapping_mul(31)
                .wrapping_add((i / CHUNK) as u8 ^ seed)
        })
        .collect::<Vec<u8>>()
        .into()
}

/// Messages on the object store's chunk subjects.
async fn chunk_messages(url: &str) -> u64 {
    let js = async_nats::jetstream::new(async_nats::connect(url).await.expect("client"));
    let stream = js
        .get_stream("OBJ_willow-blobs")
        .await
        .expect("the object store's stream");
    let mut subjects = stream
        .info_with_subjects("$O.willow-blobs.C.>")
        .await
        .expect("subjects");
    let mut n = 0;
    while let Some(s) = subjects.next().await {
        n += s.expect("subject").1 as u64;
    }
    n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn blobs_of_every_size_read_back_and_rewrites_and_deletes_leave_no_chunks() {
    let dir = tempfile::tempdir().expect("temp dir");
    let nats = Nats::start(dir.path());
    let url = nats.url();
    let config = Config::new(dir.path());
    let backend = connect(&config, &NatsOptions::new(url.clone()))
        .await
        .expect("connect");
    let blobs = backend.blobs.clone();
    let id = JobId::random();
    let sizes = [0, 1, CHUNK, CHUNK + 1, 3 * CHUNK];
    let key = |step: usize| BlobKey::Frame {
        id: id.clone(),
        step,
        welded: false,
    };
    for (step, &len) in sizes.iter().enumerate() {
        let data = pattern(len, 1);
        blobs.put(key(step), data.clone()).await.expect("put");
        let back = blobs.get(key(step)).await.expect("get").expect("stored");
        assert_eq!(back.len(), len);
        assert!(back == data, "blob of {len} bytes reads back as written");
    }
    // One chunk per started CHUNK bytes: 0 + 1 + 1 + 2 + 3.
    let expected: u64 = sizes.iter().map(|&l| l.div_ceil(CHUNK) as u64).sum();
    assert_eq!(chunk_messages(&url).await, expected);

    // Written again with other bytes: the new bytes, and the old chunks are gone.
    for (step, &len) in sizes.iter().enumerate() {
        let data = pattern(len, 2);
        blobs.put(key(step), data.clone()).await.expect("put again");
        let back = blobs.get(key(step)).await.expect("get").expect("stored");
        assert!(back == data, "blob of {len} bytes reads back as rewritten");
    }
    assert_eq!(chunk_messages(&url).await, expected);
    assert_eq!(orphan_chunks(&url).await.0, Vec::<String>::new());

    // One deleted alone, the rest with the job: nothing left.
    blobs.delete(key(4)).await.expect("delete");
    assert!(blobs.get(key(4)).await.expect("get").is_none());
    assert_eq!(chunk_messages(&url).await, expected - 3);
    blobs
        .delete_job(id.as_str())
        .await
        .expect("delete the job's blobs");
    for step in 0..sizes.len() {
        assert!(blobs.get(key(step)).await.expect("get").is_none());
    }
    assert_eq!(chunk_messages(&url).await, 0);
}

/// What a writer killed between its chunks and its info leaves (chunks no info names,
/// published here by hand) is purged by the sweep once two scans `orphan_min_age` apart
/// (zero here) found it unnamed; stored blobs are left alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_sweep_purges_chunks_no_blob_names_and_keeps_the_blobs() {
    let dir = tempfile::tempdir().expect("temp dir");
    let nats = Nats::start(dir.path());
    let url = nats.url();
    let mut options = NatsOptions::new(url.clone());
    options.orphan_min_age = Duration::ZERO;
    let backend = connect(&Config::new(dir.path()), &options)
        .await
        .expect("connect");
    let blobs = backend.blobs.clone();
    let id = JobId::random();
    let key = BlobKey::Checkpoint { id: id.clone() };
    let data = pattern(2 * CHUNK + 7, 3);
    blobs.put(key.clone(), data.clone()).await.expect("put");

    let js = async_nats::jetstream::new(async_nats::connect(url.as_str()).await.expect("client"));
    for n in 0..3u8 {
        js.publish("$O.willow-blobs.C.killedwriter", vec![n; 1000].into())
            .await
            .expect("publish")
            .await
            .expect("ack");
    }
    assert_eq!(orphan_chunks(&url).await.1, 3);
    assert_eq!(
        blobs.sweep_orphans().await.expect("first scan"),
        0,
        "a first sighting only marks"
    );
    assert_eq!(blobs.sweep_orphans().await.expect("second scan"), 1);
    assert_eq!(orphan_chunks(&url).await, (Vec::new(), 0));
    assert_eq!(chunk_messages(&url).await, 3, "the blob's own chunks stay");
    let back = blobs.get(key).await.expect("get").expect("stored");
    assert!(back == data, "the blob reads back whole");
}
