//! Small name-keyed values held inline: a run event's station and target names and its
//! per-axis maps (`axes`, `approach`). A dwell plan records two events per point, so these
//! are decoded hundreds of thousands of times per session: names of up to 24 bytes and up to
//! three axes take no heap allocation (longer ones spill to the heap, still correct).

use std::fmt;
use std::marker::PhantomData;

use serde::de::{MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use smallvec::SmallVec;

/// A name (station, target, axis): a string stored inline when short.
pub type Name = compact_str::CompactString;

/// Values by axis name, iterated in name order, one value per name: what a
/// `BTreeMap<String, T>` gives, without its per-key and per-node allocations.
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct AxisMap<T> {
    /// Sorted by name, names unique.
    entries: SmallVec<[(Name, T); 3]>,
}

impl<T> AxisMap<T> {
    pub fn new() -> Self {
        AxisMap {
            entries: SmallVec::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    fn position(&self, name: &str) -> Result<usize, usize> {
        self.entries
            .binary_search_by(|(key, _)| key.as_str().cmp(name))
    }

    pub fn get(&self, name: &str) -> Option<&T> {
        self.position(name).ok().map(|at| &self.entries[at].1)
    }

    pub fn get_mut(&mut self, name: &str) -> Option<&mut T> {
        self.position(name).ok().map(|at| &mut self.entries[at].1)
    }

    pub fn contains_key(&self, name: &str) -> bool {
        self.position(name).is_ok()
    }

    /// Sets `name`'s value, returning the one it replaces.
    pub fn insert(&mut self, name: impl Into<Name> + AsRef<str>, value: T) -> Option<T> {
        match self.position(name.as_ref()) {
            Ok(at) => Some(std::mem::replace(&mut self.entries[at].1, value)),
            Err(at) => {
                self.entries.insert(at, (name.into(), value));
                None
            }
        }
    }

    pub fn remove(&mut self, name: &str) -> Option<T> {
        self.position(name).ok().map(|at| self.entries.remove(at).1)
    }

    /// Entries in name order.
    pub fn iter(&self) -> impl DoubleEndedIterator<Item = (&Name, &T)> + ExactSizeIterator {
        self.entries.iter().map(|(key, value)| (key, value))
    }

    pub fn keys(&self) -> impl DoubleEndedIterator<Item = &Name> + ExactSizeIterator {
        self.entries.iter().map(|(key, _)| key)
    }

    pub fn values(&self) -> impl DoubleEndedIterator<Item = &T> + ExactSizeIterator {
        self.entries.iter().map(|(_, value)| value)
    }

    pub fn values_mut(&mut self) -> impl DoubleEndedIterator<Item = &mut T> + ExactSizeIterator {
        self.entries.iter_mut().map(|(_, value)| value)
    }
}

impl<T> Default for AxisMap<T> {
    fn default() -> Self {
        AxisMap::new()
    }
}

impl<T: fmt::Debug> fmt::Debug for AxisMap<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_map().entries(self.iter()).finish()
    }
}

/// A repeated name keeps its last value, as a map built by inserting does.
impl<K: Into<Name> + AsRef<str>, T> FromIterator<(K, T)> for AxisMap<T> {
    fn from_iter<I: IntoIterator<Item = (K, T)>>(entries: I) -> Self {
        let mut map = AxisMap::new();
        for (key, value) in entries {
            map.insert(key, value);
        }
        map
    }
}

impl<K: Into<Name> + AsRef<str>, T, const N: usize> From<[(K, T); N]> for AxisMap<T> {
    fn from(entries: [(K, T); N]) -> Self {
        entries.into_iter().collect()
    }
}

impl<T> IntoIterator for AxisMap<T> {
    type Item = (Name, T);
    type IntoIter = smallvec::IntoIter<[(Name, T); 3]>;

    fn into_iter(self) -> Self::IntoIter {
        self.entries.into_iter()
    }
}

impl<'a, T> IntoIterator for &'a AxisMap<T> {
    type Item = (&'a Name, &'a T);
    type IntoIter = std::iter::Map<std::slice::Iter<'a, (Name, T)>, fn(&(Name, T)) -> (&Name, &T)>;

    fn into_iter(self) -> Self::IntoIter {
        self.entries.iter().map(|(key, value)| (key, value))
    }
}

impl<T: Serialize> Serialize for AxisMap<T> {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut map = serializer.serialize_map(Some(self.len()))?;
        for (key, value) in self.iter() {
            map.serialize_entry(key.as_str(), value)?;
        }
        map.end()
    }
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for AxisMap<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Entries<T>(PhantomData<T>);

        impl<'de, T: Deserialize<'de>> Visitor<'de> for Entries<T> {
            type Value = AxisMap<T>;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("an object of values by axis name")
            }

            fn visit_map<A: MapAccess<'de>>(self, mut access: A) -> Result<Self::Value, A::Error> {
                let mut map = AxisMap::new();
                while let Some((key, value)) = access.next_entry::<Name, T>()? {
                    map.insert(key, value);
                }
                Ok(map)
            }
        }

        deserializer.deserialize_map(Entries(PhantomData))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use proptest::prelude::*;

    use super::*;

    #[test]
    fn short_names_and_three_axes_stay_inline() {
        let map = AxisMap::from([("z", 3.0), ("x", 1.0), ("y", 2.0)]);
        assert!(!map.entries.spilled());
        assert!(map.keys().all(|key| !key.is_heap_allocated()));
        let long = Name::from("a station name longer than twenty-four bytes");
        assert!(
            long.is_heap_allocated(),
            "longer names still work, on the heap"
        );
    }

    proptest! {
        /// Every operation agrees with a BTreeMap's, and the JSON is the same both ways.
        #[test]
        fn behaves_as_a_btree_map(
            entries in prop::collection::vec(("[a-e]{0,3}|[a-z]{20,30}", -5i8..5), 0..8),
            probe in "[a-e]{0,3}",
        ) {
            let ours: AxisMap<i8> = entries.iter().cloned().collect();
            let theirs: BTreeMap<String, i8> = entries.iter().cloned().collect();
            prop_assert_eq!(ours.len(), theirs.len());
            prop_assert!(ours.iter().map(|(k, v)| (k.as_str(), *v))
                .eq(theirs.iter().map(|(k, v)| (k.as_str(), *v))));
            prop_assert_eq!(ours.get(&probe), theirs.get(&probe));
            prop_assert_eq!(ours.contains_key(&probe), theirs.contains_key(&probe));
            let json = serde_json::to_string(&ours).expect("serialises");
            prop_assert_eq!(&json, &serde_json::to_string(&theirs).expect("serialises"));
            let back: AxisMap<i8> = serde_json::from_str(&json).expect("reads back");
            prop_assert!(back == ours);
            let mut ours = ours;
            let mut theirs = theirs;
            prop_assert_eq!(ours.insert(probe.as_str(), 9), theirs.insert(probe.clone(), 9));
            prop_assert_eq!(ours.remove(&entries.first().map(|e| e.0.clone()).unwrap_or_default()),
                theirs.remove(&entries.first().map(|e| e.0.clone()).unwrap_or_default()));
            prop_assert!(ours.iter().map(|(k, v)| (k.as_str(), *v))
                .eq(theirs.iter().map(|(k, v)| (k.as_str(), *v))));
        }

        /// A repeated key in the JSON keeps its last value, as serde_json's BTreeMap does.
        #[test]
        fn repeated_keys_keep_the_last_value(a in -5i8..5, b in -5i8..5) {
            let json = format!(r#"{{"x":{a},"y":0,"x":{b}}}"#);
            let ours: AxisMap<i8> = serde_json::from_str(&json).expect("reads");
            let theirs: BTreeMap<String, i8> = serde_json::from_str(&json).expect("reads");
            prop_assert!(ours.iter().map(|(k, v)| (k.as_str(), *v))
                .eq(theirs.iter().map(|(k, v)| (k.as_str(), *v))));
        }
    }
}
