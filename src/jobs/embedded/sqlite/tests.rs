use super::schema::RECOUNT_USAGE;
use super::*;
use crate::jobs::ports::{Fence, JobStore, Started, MINUTE_MS};
use crate::jobs::{JobSpec, JobState, TenantQuotas};
use willow::mesh::io::Format;

const MIN: u64 = MINUTE_MS;

fn job(tenant: &str, bytes: u64, at: u64) -> NewJob {
    NewJob {
        id: JobId::random(),
        tenant: tenant.to_string(),
        spec: JobSpec::default(),
        format: Format::Obj,
        vertex_count: 3,
        face_count: 1,
        repairs: None,
        notes: Vec::new(),
        input_bytes: bytes,
        // What its frames may store: counted with the input (`jobs::stored`).
        planned_bytes: bytes / 2,
        received: true,
        created_at: at,
        quotas: TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: 0,
            uploads_per_minute: 0,
        },
        idempotency: None,
    }
}

fn usage_rows(store: &SqliteStore) -> Vec<(String, i64, i64, i64, i64, i64)> {
    let conn = store.conn().expect("conn");
    let mut st = conn
        .prepare(
            "SELECT tenant, bytes, live, window_start, window_count, previous_count
             FROM tenant_usage ORDER BY tenant",
        )
        .expect("prepare");
    st.query_map([], |r| {
        Ok((
            r.get(0)?,
            r.get(1)?,
            r.get(2)?,
            r.get(3)?,
            r.get(4)?,
            r.get(5)?,
        ))
    })
    .expect("query")
    .collect::<Result<_, _>>()
    .expect("rows")
}

/// After every kind of change (jobs queued, started, finished, requeued, expired and
/// deleted, uploads stored and swept, over three minutes), the bytes and live jobs the
/// triggers keep equal a recount from the rows themselves, the minute windows count every
/// mesh received, and what `usage` reports follows from them.
#[tokio::test]
async fn triggers_keep_tenant_usage_equal_to_a_recount() {
    let dir = tempfile::tempdir().expect("dir");
    let store = SqliteStore::open(dir.path()).expect("open");
    let now = now_ms();
    let this_minute = now - now % MIN;
    let (earlier, previous) = (this_minute - 2 * MIN + 5, this_minute - MIN + 5);
    let id = |i: &Inserted| match i {
        Inserted::New(s) => s.id.clone(),
        other => panic!("not inserted: {other:?}"),
    };
    let mut a = Vec::new();
    for (bytes, at) in [(100, earlier), (200, previous), (300, previous), (400, now)] {
        a.push(id(&store
            .insert(job("a", bytes, at))
            .await
            .expect("insert")));
    }
    let b = id(&store.insert(job("b", 50, now)).await.expect("insert"));
    // c's job is made from a stored upload: it holds its bytes and a live job, but
    // received no mesh.
    let stored = NewJob {
        received: false,
        ..job("c", 25, now)
    };
    store.insert(stored).await.expect("insert");
    let fence = Fence::new(std::time::Duration::from_secs(30));
    store.start(&a[0], &fence, now).await.expect("start");
    store.start(&a[1], &fence, now).await.expect("start");
    store.requeue(&a[1], &fence).await.expect("requeue");
    store
        .finish(&a[0], JobState::Succeeded, None, now, now + 1, None)
        .await
        .expect("finish");
    store
        .finish(&a[2], JobState::Failed, None, now, now + 10 * MIN, None)
        .await
        .expect("finish");
    store
        .finish(&b, JobState::Cancelled, None, now, now + 10 * MIN, None)
        .await
        .expect("finish");
    store
        .put_upload("b", "u1", Format::Obj, 70, now + 1)
        .await
        .expect("upload");
    store
        .put_upload("b", "u2", Format::Obj, 80, now + 10 * MIN)
        .await
        .expect("upload");
    // a[0] and u1 expire; a[2] is deleted.
    store.sweep_expired(now + 2).await.expect("sweep");
    store.delete("a", &a[2]).await.expect("delete");
    // a[3] runs and stops early: its plan (200) comes down to what it kept (50); never up.
    store.start(&a[3], &fence, now).await.expect("start");
    store
        .settle_planned(&a[3], 50, &fence)
        .await
        .expect("settle");
    store
        .settle_planned(&a[3], 500, &fence)
        .await
        .expect("settle");

    let kept = usage_rows(&store);
    let usage = store.usage("a", now).await.expect("usage");
    assert_eq!(usage.live_jobs, 2);
    // a[1] and a[3]: 200 + 400 of input, 100 + 50 planned (a[3]'s settled).
    assert_eq!(usage.stored_bytes, 750);
    assert_eq!(
        usage.uploads_last_minute,
        MinuteWindows {
            start: this_minute,
            current: 1,
            previous: 2
        }
        .last_minute(now)
    );
    {
        let conn = store.conn().expect("conn");
        conn.execute("DELETE FROM tenant_usage", []).expect("empty");
        conn.execute(RECOUNT_USAGE, params![ms(this_minute)])
            .expect("recount");
    }
    let recounted = usage_rows(&store);
    // Bytes and live jobs equal the recount.
    let held = |rows: &[(String, i64, i64, i64, i64, i64)]| -> Vec<(String, i64, i64)> {
        rows.iter().map(|r| (r.0.clone(), r.1, r.2)).collect()
    };
    assert_eq!(held(&kept), held(&recounted));
    // By hand: a keeps a[1] (queued, 200 + 100 planned) and a[3] (running, 400 + 50
    // settled); b keeps its cancelled job (50: it never started, so its plan went) and u2
    // (80); c its job (25 + 12).
    assert_eq!(
        held(&kept),
        [
            ("a".into(), 750, 2),
            ("b".into(), 130, 0),
            ("c".into(), 37, 1)
        ]
    );
    // Nothing received: c's windows stay empty, in the triggers' rows and the recount's.
    assert_eq!((kept[2].4, kept[2].5), (0, 0));
    assert_eq!((recounted[2].4, recounted[2].5), (0, 0));
    let usage = store.usage("c", now).await.expect("usage");
    assert_eq!((usage.live_jobs, usage.uploads_last_minute), (1, 0));
    // The windows count every mesh received, also those deleted or swept since (deleting
    // jobs frees no rate): a got 2 in the previous minute and 1 in this one, b 3 in this
    // one. A recount sees only the rows still there (a[2] deleted, u1 swept).
    assert_eq!((kept[0].3, kept[0].4, kept[0].5), (ms(this_minute), 1, 2));
    // The triggers move the windows as `MinuteWindows::receive` does (the NATS store's).
    let mut expected = MinuteWindows::default();
    for at in [earlier, previous, previous, now] {
        expected.receive(at);
    }
    let as_row = |w: MinuteWindows| (ms(w.start), ms(w.current), ms(w.previous));
    assert_eq!((kept[0].3, kept[0].4, kept[0].5), as_row(expected));
    // (b's uploads take the clock's time: if a minute started during the test, b's windows
    // moved on and its 3 are split over them.)
    let b_received = match kept[1].3 - ms(this_minute) {
        0 => {
            assert_eq!(kept[1].5, 0, "b received nothing before this minute");
            kept[1].4
        }
        d if d == ms(MIN) => kept[1].4 + kept[1].5,
        other => panic!("b's windows start {other} ms after the test's minute"),
    };
    assert_eq!(b_received, 3);
    assert_eq!((recounted[0].4, recounted[0].5), (1, 1));
    assert_eq!((recounted[1].4, recounted[1].5), (2, 0));

    // A tenant with no rows holds nothing of its own; the server's total is every tenant's.
    let unknown = store.usage("nobody", now).await.expect("usage");
    assert_eq!(
        unknown,
        Usage {
            server_stored_bytes: 750 + 130 + 37,
            ..Usage::default()
        }
    );
}

/// A database that can grow no more (`max_page_count` at its size: SQLite answers SQLITE_FULL
/// as on a full disk) refuses new jobs with `storage_full`, and still deletes a finished job,
/// frees its rows and reads the rest.
#[tokio::test]
async fn a_full_database_refuses_inserts_as_storage_full_and_still_deletes() {
    let dir = tempfile::tempdir().expect("dir");
    let store = SqliteStore::open(dir.path()).expect("open");
    let now = now_ms();
    let (kept, doomed) = (job("t", 10, now), job("t", 10, now));
    for j in [&kept, &doomed] {
        assert!(matches!(
            store.insert(j.clone()).await.expect("insert"),
            Inserted::New(_)
        ));
        store
            .finish(
                j.id.as_str(),
                JobState::Succeeded,
                None,
                now,
                now + 60 * MIN,
                None,
            )
            .await
            .expect("finish");
    }
    {
        let conn = store.conn().expect("conn");
        // Everything in the main file, then no page more.
        conn.execute_batch("PRAGMA wal_checkpoint(TRUNCATE)")
            .expect("checkpoint");
        let pages: i64 = conn
            .query_row("PRAGMA page_count", [], |r| r.get(0))
            .expect("page_count");
        conn.pragma_update(None, "max_page_count", pages)
            .expect("max_page_count");
    }
    let mut refused = None;
    // Fill the free room in the last pages, then the next job needs a page more.
    for _ in 0..10_000 {
        if let Err(e) = store.insert(job("t", 10, now)).await {
            refused = Some(e);
            break;
        }
    }
    let refused = refused.expect("the database filled up");
    assert_eq!(refused.code(), "storage_full", "{refused:?}");
    store
        .delete("t", doomed.id.as_str())
        .await
        .expect("delete on a full database");
    assert_eq!(
        store
            .status(doomed.id.as_str(), None)
            .await
            .map_err(|e| e.code())
            .err(),
        Some("not_found")
    );
    let read = store.status(kept.id.as_str(), None).await.expect("read");
    assert_eq!(read.state, JobState::Succeeded);
}

/// The delivery ledger counts the deliveries in a row that found no newer checkpoint: a run
/// that died after a checkpoint starts the count again, one that died before does not, and
/// a hand-back in order (requeue) starts it afresh. Cases worked by hand: deliveries d1..d6
/// with checkpoints written between some of them.
#[tokio::test]
async fn deliveries_count_only_runs_that_made_no_progress() {
    let dir = tempfile::tempdir().expect("dir");
    let store = SqliteStore::open(dir.path()).expect("open");
    let id = match store.insert(job("a", 10, now_ms())).await.expect("insert") {
        Inserted::New(s) => s.id,
        other => panic!("not inserted: {other:?}"),
    };
    let fence = Fence::new(std::time::Duration::from_secs(30));
    let started = store.start(&id, &fence, now_ms()).await.expect("start");
    assert!(matches!(started, Started::Run(_)));
    // d1: a new job, no checkpoint: the first of its run.
    assert_eq!(store.delivered(&id, &fence).await.expect("d1"), 1);
    // Died before any checkpoint: d2 is the second in a row.
    assert_eq!(store.delivered(&id, &fence).await.expect("d2"), 2);
    // d2's run reached the checkpoint at step 40 and died: d3 starts over.
    store
        .checkpointed(&id, 40, &fence)
        .await
        .expect("checkpoint");
    assert_eq!(store.delivered(&id, &fence).await.expect("d3"), 1);
    // d3 died without a newer checkpoint (the same step written again is no progress).
    store
        .checkpointed(&id, 40, &fence)
        .await
        .expect("checkpoint");
    assert_eq!(store.delivered(&id, &fence).await.expect("d4"), 2);
    assert_eq!(store.delivered(&id, &fence).await.expect("d5"), 3);
    // Handed back in order (shutdown): the next delivery is the first of a fresh count.
    store.requeue(&id, &fence).await.expect("requeue");
    let started = store.start(&id, &fence, now_ms()).await.expect("start");
    assert!(matches!(started, Started::Run(_)));
    assert_eq!(store.delivered(&id, &fence).await.expect("d6"), 1);
    assert!(matches!(
        store.delivered("j_unknown", &fence).await,
        Err(JobError::NotFound(_))
    ));
}
