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
                let $v = <$inner as serde::Deserialize>::deserialize(d)?;
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
