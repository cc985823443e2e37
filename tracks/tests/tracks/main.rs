//! The track library's integration tests, one module a concern, in one test binary (one link
//! instead of three on every build).

mod file_properties;
mod paper_maps;
mod raceline_all_maps;
