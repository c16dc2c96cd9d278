//! The test bed's heavy tests, run one at a time after the others: the agent on an emulated
//! Raspberry Pi 5, the operator image, a real node, and the Helm chart on it (with the install
//! page walked as written, module `walk`).
//!
//! One test binary per group, a module per file: the harness is linked once per group.

mod arm64;
mod cluster;
mod image;
mod node;
mod walk;
