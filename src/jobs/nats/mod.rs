//! The NATS JetStream backend (see [`super::ports`]).
