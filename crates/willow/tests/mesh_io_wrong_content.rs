//! Content that is not what it was sent as gets an error that says what it is (issue 27,
//! item 5): OFF or ASCII STL sent as OBJ, gzip bodies; a glTF JSON with a byte order mark and
//! CR-only line ends are understood.

use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::MeshError;

fn refuse(bytes: &[u8], format: Format) -> MeshError {
    Asset::read(bytes, format, &Limits::default()).expect_err("must be refused")
}

const TETRA_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n";
const TETRA_OFF: &str =
    "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n";

#[test]
fn off_sent_as_obj_names_off() {
    let e = refuse(TETRA_OFF.as_bytes(), Format::Obj);
    assert_eq!(e.code(), "format_mismatch");
    assert_eq!(
        e.to_string(),
        "the file was sent as OBJ but it is OFF: send it as OFF (Content-Type model/x-off, \
         or a .off file name)"
    );
    // Sent as what it is, it reads.
    let a = Asset::read(TETRA_OFF.as_bytes(), Format::Off, &Limits::default()).unwrap();
    assert_eq!(a.surface().face_count(), 4);
}

#[test]
fn ascii_stl_sent_as_obj_names_stl() {
    let tetra = Asset::read(TETRA_OBJ.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let stl = tetra
        .write(&tetra.surface().positions, Format::Stl)
        .unwrap();
    // Binary STL from the writer; an ASCII one written by hand.
    let mut ascii = String::from("solid tetra\n");
    for t in &tetra.surface().triangles {
        ascii += "facet normal 0 0 0\nouter loop\n";
        for &v in t {
            let p = tetra.surface().positions[v];
            ascii += &format!("vertex {} {} {}\n", p[0], p[1], p[2]);
        }
        ascii += "endloop\nendfacet\n";
    }
    ascii += "endsolid tetra\n";
    for bytes in [ascii.as_bytes(), &stl[..]] {
        let e = refuse(bytes, Format::Obj);
        assert_eq!(e.code(), "format_mismatch", "{e}");
        assert!(e.to_string().contains("but it is STL"), "{e}");
        assert!(e.to_string().contains("model/stl"), "{e}");
    }
}

#[test]
fn gzip_body_says_gzip() {
    // The gzip member header (RFC 1952): magic, deflate, no flags; what follows is irrelevant.
    let gz = [
        0x1f, 0x8b, 0x08, 0x00, 0, 0, 0, 0, 0, 0x03, 0x2b, 0x53, 0x30, 0x54,
    ];
    for f in [Format::Obj, Format::Glb, Format::Ply, Format::Stl] {
        let e = refuse(&gz, f);
        assert_eq!(e.code(), "not_a_mesh");
        assert!(e.to_string().contains("gzip-compressed"), "{e}");
    }
}

#[test]
fn gltf_json_with_a_byte_order_mark_is_accepted() {
    let tetra = Asset::read(TETRA_OBJ.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let json = tetra
        .write(&tetra.surface().positions, Format::Gltf)
        .unwrap();
    let mut with_bom = b"\xEF\xBB\xBF".to_vec();
    with_bom.extend_from_slice(&json);
    for f in [Format::Gltf, Format::Glb] {
        let a = Asset::read(&with_bom, f, &Limits::default()).unwrap();
        assert_eq!(a.surface(), tetra.surface(), "read as {f:?}");
    }
}

#[test]
fn cr_only_line_ends_are_lines() {
    let cr = TETRA_OBJ.replace('\n', "\r");
    let a = Asset::read(cr.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    let lf = Asset::read(TETRA_OBJ.as_bytes(), Format::Obj, &Limits::default()).unwrap();
    assert_eq!(a.surface(), lf.surface());
    assert_eq!(a.file_vertex_count(), 4);
    // Written back with its own line ends, moved.
    let moved: Vec<[f64; 3]> = a
        .surface()
        .positions
        .iter()
        .map(|p| p.map(|x| 2.0 * x))
        .collect();
    let out = String::from_utf8(a.write(&moved, Format::Obj).unwrap()).unwrap();
    assert!(
        !out.contains('\n') && out.matches('\r').count() == 8,
        "{out:?}"
    );
    assert!(out.starts_with("v 0 0 0\rv 2 0 0\r"), "{out:?}");
    // OFF and ASCII STL with CR-only line ends too.
    let off = Asset::read(
        TETRA_OFF.replace('\n', "\r").as_bytes(),
        Format::Off,
        &Limits::default(),
    )
    .unwrap();
    assert_eq!(off.surface().face_count(), 4);
}
