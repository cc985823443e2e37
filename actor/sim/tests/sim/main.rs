//! The simulator's integration tests, one module a concern, in one test binary (each binary
//! links the whole simulator again: one instead of nine saves their links on every build).

mod every_key;
mod follow_the_gap;
mod lidar_on_maps;
mod policy_rival;
mod race_agents;
mod race_env;
mod rival_contexts;
mod vector;
mod vehicle_reference;
