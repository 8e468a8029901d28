//! FairCurve: a noisy curve rounded, hostile input refused.

use super::*;

/// r = 1 + 0.2 sin 5t plus a deterministic jitter, as packed x, y.
fn noisy_closed_curve(n: usize) -> Vec<f64> {
    (0..n)
        .flat_map(|i| {
            let t = std::f64::consts::TAU * i as f64 / n as f64;
            let jitter = 0.01 * (((i * 7919) % 13) as f64 / 13.0 - 0.5);
            let r = 1.0 + 0.2 * (5.0 * t).sin() + jitter;
            [r * t.cos(), r * t.sin()]
        })
        .collect()
}

/// The library's measures of a closed curve: (σ(κ)/κ̄ with its own dual lengths, length).
fn curve_measures(xy: &[f64]) -> (f64, f64) {
    use willow::curve::{curvature_std_over_mean, dual_lengths, Curve};
    let points: Vec<[f64; 2]> = xy.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
    let curve = Curve::new(points, true).expect("valid curve");
    let mut dual = vec![0.0; curve.points.len()];
    dual_lengths(&curve.edge_lengths(), true, &mut dual);
    (
        curvature_std_over_mean(&curve.curvature(), &dual),
        curve.length(),
    )
}

fn curve_request(xy: Vec<f64>, closed: bool) -> v1::FairCurveRequest {
    v1::FairCurveRequest {
        curve: Some(v1::Curve { xy, closed }),
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fair_curve_rounds_a_noisy_curve_and_refuses_hostile_input() {
    let server = Server::start(|c| {
        c.limits.max_curve_points = 60_000;
        c.limits.max_curve_frame_points = 5_000;
    })
    .await;
    let mut client = server.fairing().await;
    let input = noisy_closed_curve(256);
    let (before, length) = curve_measures(&input);
    assert!(before > 0.5, "noisy: σ/κ̄ = {before}");

    let out = client
        .fair_curve(v1::FairCurveRequest {
            steps: Some(6),
            ..curve_request(input.clone(), true)
        })
        .await
        .expect("FairCurve")
        .into_inner();
    let curve = out.curve.expect("curve");
    assert!(curve.closed);
    assert_eq!(curve.xy.len(), input.len());
    let (after, new_length) = curve_measures(&curve.xy);
    assert!(after < 1e-2 * before, "σ/κ̄ from {before} to {after}");
    assert!(
        (new_length / length - 1.0).abs() < 1e-3,
        "{length} → {new_length}"
    );
    assert_eq!(out.metrics.len(), 7);
    assert_eq!(out.metrics.last().map(|m| m.step), Some(6));
    assert!((out.metrics[6].curvature_std_over_mean - after).abs() < 1e-3);
    assert_eq!((out.steps, out.tau, out.frame_interval), (6, 0.5, 0));
    assert_eq!(
        out.deadline.map(|d| d.seconds),
        Some(10),
        "the server default"
    );
    assert!(out.frames.is_empty());

    let out = client
        .fair_curve(v1::FairCurveRequest {
            steps: Some(5),
            frame_interval: 2,
            ..curve_request(input.clone(), true)
        })
        .await
        .expect("FairCurve with frames")
        .into_inner();
    let steps: Vec<u32> = out.frames.iter().map(|f| f.step).collect();
    assert_eq!(steps, vec![0, 2, 4, 5]);
    assert_eq!(
        out.frames[0].curve.as_ref().map(|c| &c.xy),
        Some(&input),
        "frame 0 is the input, bit for bit"
    );
    assert_eq!(out.frames[3].curve, out.curve);

    // Hostile input: each refused with the field (and for curves, the reason) named.
    let reason = |s: &Status| {
        s.get_details_error_info()
            .map(|e| e.reason)
            .unwrap_or_default()
    };
    let mut repeated = input.clone();
    repeated.extend_from_slice(&input[..2]);
    let mut nan = input.clone();
    nan[7] = f64::NAN;
    // A good request with one field set wrong.
    let with = |edit: fn(&mut v1::FairCurveRequest)| {
        let mut r = curve_request(input.clone(), true);
        edit(&mut r);
        r
    };
    fn seconds(seconds: i64) -> prost_types::Duration {
        prost_types::Duration { seconds, nanos: 0 }
    }
    for (request, field, why) in [
        (curve_request(input[..5].to_vec(), true), "curve.xy", ""),
        (curve_request(nan, true), "curve.xy", "NON_FINITE"),
        (
            curve_request(repeated, true),
            "curve.xy",
            "ZERO_LENGTH_EDGE",
        ),
        (
            curve_request(vec![0.0, 0.0, 1.0, 0.0], true),
            "curve.xy",
            "TOO_FEW_POINTS",
        ),
        (
            curve_request(Vec::new(), false),
            "curve.xy",
            "TOO_FEW_POINTS",
        ),
        (
            curve_request(vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0], false),
            "curve.xy",
            "CUSP",
        ),
        (v1::FairCurveRequest::default(), "curve", ""),
        (with(|r| r.steps = Some(0)), "steps", ""),
        (with(|r| r.steps = Some(5000)), "steps", ""),
        (with(|r| r.tau = Some(1.0)), "tau", ""),
        (with(|r| r.tau = Some(f64::NAN)), "tau", ""),
        (with(|r| r.deadline = Some(seconds(0))), "deadline", ""),
        (with(|r| r.deadline = Some(seconds(1000))), "deadline", ""),
        // 256 points × 101 frames is over this server's 5000 frame points.
        (
            with(|r| {
                r.steps = Some(100);
                r.frame_interval = 1;
            }),
            "frame_interval",
            "",
        ),
    ] {
        let status = client.fair_curve(request).await.expect_err("refused");
        assert_eq!(
            status.code(),
            Code::InvalidArgument,
            "{field}: {}",
            status.message()
        );
        assert_eq!(violations(&status), vec![field.to_string()], "{status:?}");
        if !why.is_empty() {
            assert_eq!(reason(&status), why, "{}", status.message());
        }
    }
    // Too many points: a named quota, like an oversized mesh.
    let status = client
        .fair_curve(curve_request(noisy_closed_curve(60_001), true))
        .await
        .expect_err("too many points");
    assert_eq!(status.code(), Code::ResourceExhausted);
    let quota = status
        .get_details_quota_failure()
        .map(|q| {
            q.violations
                .into_iter()
                .map(|v| v.subject)
                .collect::<Vec<_>>()
        })
        .unwrap_or_default();
    assert_eq!(quota, vec!["curve points".to_string()]);
    // The request's deadline ends a long run (50k points, 1000 steps) with DEADLINE_EXCEEDED.
    let status = client
        .fair_curve(v1::FairCurveRequest {
            steps: Some(1000),
            deadline: Some(prost_types::Duration {
                seconds: 0,
                nanos: 300_000_000,
            }),
            ..curve_request(noisy_closed_curve(50_000), true)
        })
        .await
        .expect_err("over its deadline");
    assert_eq!(
        status.code(),
        Code::DeadlineExceeded,
        "{}",
        status.message()
    );
    assert!(
        status.message().contains("deadline of 0.3 s"),
        "{}",
        status.message()
    );
}
