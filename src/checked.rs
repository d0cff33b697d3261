//! Values checked as they are read: a newtype whose `Deserialize` refuses what is out of
//! range, so a parser's error carries the file's line and column (RON reports the position of
//! the value that failed). Used by the sidecar and the envmap file.

/// `checked!(/// doc  Name(inner), "schema type", |v| condition, "message with {}")`: a
/// transparent newtype over `inner` that deserialises only values meeting the condition.
macro_rules! checked {
    ($(#[$doc:meta])* $name:ident($inner:ty), $schema:literal, |$v:ident| $check:expr, $msg:expr) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, schemars::JsonSchema)]
        #[serde(transparent)]
        pub struct $name(#[schemars(with = $schema)] pub $inner);

        impl<'de> serde::Deserialize<'de> for $name {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
                let $v = <$inner as $crate::checked::Read>::read(d)?;
                if $check {
                    Ok($name($v))
                } else {
                    Err(serde::de::Error::custom(format!($msg, $v)))
                }
            }
        }
    };
}

pub(crate) use checked;

/// How a checked value's inner type is read: as serde reads it, except that three numbers
/// are read from a RON tuple `(x, y, z)` or a list `[x, y, z]` alike (the JSON Schema, which
/// has no tuples, calls them an array; JSON habits write lists). They are written as tuples.
pub trait Read<'de>: Sized {
    fn read<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error>;
}

impl<'de> Read<'de> for u32 {
    fn read<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        serde::Deserialize::deserialize(d)
    }
}

impl<'de> Read<'de> for f32 {
    fn read<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        serde::Deserialize::deserialize(d)
    }
}

impl<'de> Read<'de> for (f32, f32, f32) {
    fn read<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Three;
        impl<'de> serde::de::Visitor<'de> for Three {
            type Value = (f32, f32, f32);
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("three numbers, as (x, y, z) or [x, y, z]")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Self::Value, A::Error> {
                let mut v = [0f32; 3];
                for (i, slot) in v.iter_mut().enumerate() {
                    *slot = seq
                        .next_element()?
                        .ok_or_else(|| serde::de::Error::invalid_length(i, &self))?;
                }
                if seq.next_element::<serde::de::IgnoredAny>()?.is_some() {
                    return Err(serde::de::Error::invalid_length(4, &self));
                }
                Ok((v[0], v[1], v[2]))
            }
        }
        d.deserialize_any(Three)
    }
}
