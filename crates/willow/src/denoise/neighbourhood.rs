//! The face neighbourhoods normal filtering works on, built once from the connectivity (and,
//! for the filter's geometric disc, the input's centroids): compressed rows, one per face.

use crate::geometry::vec3::{norm, sub};

/// Rows of indices, one per face (compressed sparse rows).
#[derive(Clone, Debug, Default)]
pub struct Rows {
    pub start: Vec<usize>,
    pub items: Vec<usize>,
}

impl Rows {
    pub fn row(&self, i: usize) -> &[usize] {
        &self.items[self.start[i]..self.start[i + 1]]
    }

    pub fn len(&self) -> usize {
        self.start.len().saturating_sub(1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn from_lists<I: IntoIterator<Item = usize>>(lists: impl Iterator<Item = I>) -> Rows {
        let mut rows = Rows {
            start: vec![0],
            items: Vec::new(),
        };
        for list in lists {
            rows.items.extend(list);
            rows.start.push(rows.items.len());
        }
        rows
    }
}

/// The faces around each vertex.
pub fn vertex_faces(vertex_count: usize, triangles: &[[usize; 3]]) -> Rows {
    let mut count = vec![0usize; vertex_count + 1];
    for t in triangles {
        for &v in t {
            count[v + 1] += 1;
        }
    }
    for i in 0..vertex_count {
        count[i + 1] += count[i];
    }
    let mut fill = count.clone();
    let mut items = vec![0usize; count[vertex_count]];
    for (f, t) in triangles.iter().enumerate() {
        for &v in t {
            items[fill[v]] = f;
            fill[v] += 1;
        }
    }
    Rows {
        start: count,
        items,
    }
}

/// Each face's vertex ring: itself and every face sharing a vertex with it, each once, the
/// face itself first. The patches of guided filtering (Zhang et al. 2015, §4.1).
pub fn face_rings(triangles: &[[usize; 3]], vertex_faces: &Rows) -> Rows {
    let mut mark = vec![usize::MAX; triangles.len()];
    Rows::from_lists(triangles.iter().enumerate().map(|(f, t)| {
        let mut ring = vec![f];
        mark[f] = f;
        for &v in t {
            for &g in vertex_faces.row(v) {
                if mark[g] != f {
                    mark[g] = f;
                    ring.push(g);
                }
            }
        }
        ring
    }))
}

/// For each face `j`, the pairs of edge-adjacent faces that both lie in `j`'s ring: the
/// patch's inner edges, over which Zhang et al.'s relative total variation sums (§4.1).
pub fn patch_inner_edges(
    rings: &Rows,
    edge_faces: &[[Option<usize>; 2]],
    face_edges: &[[usize; 3]],
) -> Vec<Vec<[usize; 2]>> {
    let mut mark = vec![usize::MAX; face_edges.len()];
    let mut edge_seen = vec![usize::MAX; edge_faces.len()];
    (0..rings.len())
        .map(|j| {
            let ring = rings.row(j);
            for &f in ring {
                mark[f] = j;
            }
            let mut pairs = Vec::new();
            for &f in ring {
                for &e in &face_edges[f] {
                    if edge_seen[e] == j {
                        continue;
                    }
                    edge_seen[e] = j;
                    if let [Some(a), Some(b)] = edge_faces[e] {
                        if mark[a] == j && mark[b] == j {
                            pairs.push([a, b]);
                        }
                    }
                }
            }
            pairs
        })
        .collect()
}

/// Mean distance between the centroids of edge-adjacent faces: the length scale of the
/// filter's spatial weight and disc (Zhang et al. 2015, §5).
pub fn mean_adjacent_centroid_distance(
    centroids: &[[f64; 3]],
    edge_faces: &[[Option<usize>; 2]],
) -> f64 {
    let (mut sum, mut count) = (0.0, 0usize);
    for pair in edge_faces {
        if let [Some(a), Some(b)] = *pair {
            sum += norm(sub(centroids[a], centroids[b]));
            count += 1;
        }
    }
    if count == 0 {
        0.0
    } else {
        sum / count as f64
    }
}

/// Each face's geometric disc: the faces reachable through vertex rings whose centroids lie
/// within `radius` of its own, itself first (the reference implementation's
/// "geometrical" neighbourhood).
pub fn centroid_discs(centroids: &[[f64; 3]], rings: &Rows, radius: f64) -> Rows {
    let n = centroids.len();
    let mut mark = vec![usize::MAX; n];
    let mut queue = Vec::new();
    let r2 = radius * radius;
    Rows::from_lists((0..n).map(|f| {
        let c = centroids[f];
        let mut disc = vec![f];
        mark[f] = f;
        queue.clear();
        queue.push(f);
        let mut head = 0;
        while head < queue.len() {
            let g = queue[head];
            head += 1;
            for &h in rings.row(g) {
                if mark[h] == f {
                    continue;
                }
                mark[h] = f;
                let d = sub(centroids[h], c);
                if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2 {
                    disc.push(h);
                    queue.push(h);
                }
            }
        }
        disc
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::icosphere;
    use crate::mesh::topology::Topology;

    #[test]
    fn a_closed_surfaces_rings_hold_every_face_sharing_a_vertex() {
        let mesh = icosphere(2);
        let vf = vertex_faces(mesh.vertex_count(), &mesh.triangles);
        let rings = face_rings(&mesh.triangles, &vf);
        for f in 0..mesh.face_count() {
            let ring = rings.row(f);
            assert_eq!(ring[0], f);
            for g in 0..mesh.face_count() {
                let shares = mesh.triangles[f]
                    .iter()
                    .any(|v| mesh.triangles[g].contains(v));
                assert_eq!(shares, ring.contains(&g), "faces {f} and {g}");
            }
        }
        // On an icosphere every vertex has valence 5 or 6, so a ring has 10 to 13 faces.
        assert!((0..mesh.face_count()).all(|f| (10..=13).contains(&rings.row(f).len())));
    }

    #[test]
    fn a_patchs_inner_edges_join_faces_of_the_patch() {
        let mesh = icosphere(2);
        let topology = Topology::new(&mesh);
        let vf = vertex_faces(mesh.vertex_count(), &mesh.triangles);
        let rings = face_rings(&mesh.triangles, &vf);
        let inner = patch_inner_edges(&rings, &topology.edge_faces, &topology.face_edges);
        for (j, pairs) in inner.iter().enumerate() {
            let ring = rings.row(j);
            assert!(!pairs.is_empty());
            for [a, b] in pairs {
                assert!(ring.contains(a) && ring.contains(b));
            }
            // A ring is connected through its edges, so it has at least k − 1 inner edges.
            assert!(pairs.len() >= ring.len() - 1);
        }
    }

    #[test]
    fn a_disc_of_radius_zero_is_the_face_alone_and_a_huge_one_is_everything() {
        let mesh = icosphere(1);
        let vf = vertex_faces(mesh.vertex_count(), &mesh.triangles);
        let rings = face_rings(&mesh.triangles, &vf);
        let centroids: Vec<[f64; 3]> = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| mesh.positions[v]);
                [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0)
            })
            .collect();
        let none = centroid_discs(&centroids, &rings, 0.0);
        let all = centroid_discs(&centroids, &rings, 10.0);
        for f in 0..mesh.face_count() {
            assert_eq!(none.row(f), &[f]);
            assert_eq!(all.row(f).len(), mesh.face_count());
        }
    }
}
