//! Far from the origin (map-grid coordinates), GLB and glTF results keep 1e-6 of the model's
//! size (issue 27, item 4): positions are stored relative to a node translation, which the
//! JSON holds in f64, instead of as f32 coordinates that snap to a 0.5 grid at 5e6.

use willow::mesh::generate::bumpy_sphere;
use willow::mesh::io::{Asset, Format, Limits};

fn obj_at(offset: f64) -> String {
    let m = bumpy_sphere(2, 0.1);
    let mut s = String::new();
    for p in &m.positions {
        s += &format!(
            "v {} {} {}\n",
            p[0] + offset,
            p[1] - offset,
            p[2] + 0.5 * offset
        );
    }
    for t in &m.triangles {
        s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

fn size(p: &[[f64; 3]]) -> f64 {
    (0..3)
        .map(|k| {
            let (lo, hi) = p
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), q| {
                    (l.min(q[k]), h.max(q[k]))
                });
            hi - lo
        })
        .fold(0.0, f64::max)
}

#[test]
fn glb_and_gltf_keep_a_millionth_of_the_size_at_5e6_and_1e9() {
    for offset in [5e6, 1e9] {
        let a = Asset::read(obj_at(offset).as_bytes(), Format::Obj, &Limits::default()).unwrap();
        let p = &a.surface().positions;
        let tol = 1e-6 * size(p);
        // What plain f32 coordinates would lose, so the test can fail: half an ulp at `offset`.
        assert!(offset * f64::from(f32::EPSILON) / 2.0 > 10.0 * tol);
        for f in [Format::Glb, Format::Gltf] {
            let out = a.write(p, f).unwrap();
            let b = Asset::read(&out, f, &Limits::default()).unwrap();
            assert_eq!(b.surface().vertex_count(), p.len());
            // Each read-back vertex against its nearest original (they are ≥ 0.05 apart;
            // welding may number them in another order).
            let dist = |x: &[f64; 3], y: &[f64; 3]| {
                (0..3).map(|k| (x[k] - y[k]).abs()).fold(0.0, f64::max)
            };
            let worst = b
                .surface()
                .positions
                .iter()
                .map(|x| p.iter().map(|y| dist(x, y)).fold(f64::INFINITY, f64::min))
                .fold(0.0, f64::max);
            assert!(worst < tol, "{f:?} at {offset}: {worst} vs {tol}");
        }
        let json: serde_json::Value =
            serde_json::from_slice(&a.write(p, Format::Gltf).unwrap()).unwrap();
        let t = json["nodes"][0]["translation"]
            .as_array()
            .expect("a translation");
        assert!((t[0].as_f64().unwrap() - offset).abs() < 2.0, "{t:?}");
    }
    // Around the origin nothing changes: no translation.
    let a = Asset::read(obj_at(0.0).as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&a.write(&a.surface().positions, Format::Gltf).unwrap()).unwrap();
    assert!(json["nodes"][0].get("translation").is_none());
}
