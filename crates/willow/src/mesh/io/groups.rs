//! Named groups of faces a file carries: OBJ `g` and `o` names, glTF node and mesh names.
//! They let a user name a part of their file (`{"group": "ear"}`, issue 29) in the file's own
//! terms. Faces are numbered as the surface's faces ([`super::Asset::surface`]), which follow
//! the file's triangles in order.

use super::Source;
use std::ops::Range;

/// Face ranges per name, in order of first appearance. A name may cover several runs of
/// faces (an OBJ `g` line repeated, a glTF mesh instanced by two nodes).
#[derive(Clone, Debug, Default)]
pub(crate) struct Groups {
    names: Vec<String>,
    faces: Vec<Vec<Range<usize>>>,
}

impl Groups {
    /// The slot of `name`, made when it is new.
    pub(crate) fn slot(&mut self, name: &str) -> usize {
        match self.names.iter().position(|n| n == name) {
            Some(k) => k,
            None => {
                self.names.push(name.to_owned());
                self.faces.push(Vec::new());
                self.names.len() - 1
            }
        }
    }

    /// Adds the faces `range` to the group in `slot`, merging with the run before it.
    pub(crate) fn add(&mut self, slot: usize, range: Range<usize>) {
        if range.is_empty() {
            return;
        }
        let Some(runs) = self.faces.get_mut(slot) else {
            return;
        };
        match runs.last_mut() {
            Some(last) if last.end == range.start => last.end = range.end,
            _ => runs.push(range),
        }
    }

    /// The names of the groups that hold at least one face, in file order.
    pub(crate) fn names(&self) -> Vec<&str> {
        self.names
            .iter()
            .zip(&self.faces)
            .filter(|(_, f)| !f.is_empty())
            .map(|(n, _)| n.as_str())
            .collect()
    }

    /// The faces of the group `name`, or `None` when no face carries it.
    pub(crate) fn faces(&self, name: &str) -> Option<impl Iterator<Item = usize> + '_> {
        let k = self.names.iter().position(|n| n == name)?;
        let runs = self.faces.get(k)?;
        (!runs.is_empty()).then(|| runs.iter().flat_map(|r| r.clone()))
    }
}

impl super::Asset {
    /// The names of the file's face groups: OBJ `g` and `o` names, glTF node and mesh names
    /// (each with at least one face), in file order.
    pub fn group_names(&self) -> Vec<&str> {
        match self.groups() {
            Some((groups, _)) => groups.names(),
            // Made in code, or a format without names: no groups.
            None => Vec::new(),
        }
    }

    /// The file's face groups, and the number of faces of this asset per face of the
    /// groups' (4^levels for a refined asset: the children follow their parent).
    fn groups(&self) -> Option<(&Groups, usize)> {
        let (source, per_face) = match &self.source {
            Source::Refined(r) => (r.original.as_ref(), 1usize << (2 * r.levels)),
            other => (other, 1),
        };
        match source {
            Source::Obj(src) => Some((&src.groups, per_face)),
            Source::Gltf(src) => Some((&src.groups, per_face)),
            _ => None,
        }
    }

    /// The surface vertices ([`Asset::surface`]) of the faces in the group `name` (see
    /// [`Asset::group_names`]), ascending; `None` when no face of the file carries the name.
    pub fn group_vertices(&self, name: &str) -> Option<Vec<usize>> {
        let (groups, per_face) = self.groups()?;
        let faces: Vec<usize> = groups
            .faces(name)?
            .flat_map(|f| f * per_face..(f + 1) * per_face)
            .collect();
        let mut in_group = vec![false; self.surface.vertex_count()];
        for f in faces {
            for &v in self.surface.triangles.get(f).into_iter().flatten() {
                in_group[v] = true;
            }
        }
        Some((0..in_group.len()).filter(|&v| in_group[v]).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_merge_and_names_list_only_groups_with_faces() {
        let mut g = Groups::default();
        let a = g.slot("a");
        let b = g.slot("b");
        g.slot("empty");
        g.add(a, 0..2);
        g.add(a, 2..3);
        g.add(b, 3..5);
        g.add(a, 7..8);
        assert_eq!(g.slot("a"), a);
        assert_eq!(g.names(), vec!["a", "b"]);
        let faces: Vec<usize> = g.faces("a").expect("a").collect();
        assert_eq!(faces, vec![0, 1, 2, 7]);
        assert!(g.faces("empty").is_none());
        assert!(g.faces("c").is_none());
    }
}
