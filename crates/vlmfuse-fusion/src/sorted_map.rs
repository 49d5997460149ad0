//! `#[serde(with = "crate::sorted_map")]` for the engine's hash maps: written in key order, so
//! that a serialised engine is a function of its state alone (a `HashMap` iterates in a random
//! order per process, and two equal engines would otherwise serialise to different bytes).

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::collections::{BTreeMap, HashMap};
use std::hash::Hash;

pub fn serialize<K, V, S>(m: &HashMap<K, V>, s: S) -> Result<S::Ok, S::Error>
where
    K: Ord + Serialize,
    V: Serialize,
    S: Serializer,
{
    m.iter().collect::<BTreeMap<&K, &V>>().serialize(s)
}

pub fn deserialize<'de, K, V, D>(d: D) -> Result<HashMap<K, V>, D::Error>
where
    K: Eq + Hash + Deserialize<'de>,
    V: Deserialize<'de>,
    D: Deserializer<'de>,
{
    HashMap::<K, V>::deserialize(d)
}

/// `#[serde(with = "crate::sorted_map::as_json")]`: a field written as its JSON text. For the
/// engine's setup (configuration, ontology), whose serde forms skip absent optional fields: a
/// compact binary format (the store's snapshots) cannot tell a skipped field from the next one,
/// but JSON names them.
pub mod as_json {
    use serde::de::DeserializeOwned;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<T: Serialize, S: Serializer>(v: &T, s: S) -> Result<S::Ok, S::Error> {
        serde_json::to_string(v)
            .map_err(serde::ser::Error::custom)?
            .serialize(s)
    }

    pub fn deserialize<'de, T: DeserializeOwned, D: Deserializer<'de>>(
        d: D,
    ) -> Result<T, D::Error> {
        let text = String::deserialize(d)?;
        serde_json::from_str(&text).map_err(serde::de::Error::custom)
    }
}
