//! A robot's identity, the key of everything the operator keeps about it.

use std::fmt;

/// A robot's identity: its Robot resource's namespace and name, the key of everything stored.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RobotKey {
    /// Namespace of the Robot resource.
    pub namespace: String,
    /// Name of the Robot resource.
    pub name: String,
}

impl RobotKey {
    /// The robot `namespace/name`.
    pub fn new(namespace: impl Into<String>, name: impl Into<String>) -> Self {
        Self {
            namespace: namespace.into(),
            name: name.into(),
        }
    }
}

impl fmt::Display for RobotKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.namespace, self.name)
    }
}
