//! A ctxrace run's data: the run folder (its lock, its preparation and resume rule) and its
//! files (written atomically, links never followed), the result rows on disk, one env step as the actors report it, and the traits a
//! single-process trainer runs on (`experience`: an experience source and a sample store); a
//! checkpoint's read side ([`checkpoint`]: its seal checked, a run's checkpoints) and a trained
//! agent read back from one ([`trained`]).

pub mod checkpoint;
pub mod experience;
pub mod lock;
pub mod path_error;
pub mod results;
pub mod run_dir;
pub mod run_folder;
pub mod steps;
pub mod trained;

pub use steps::TrajectoryStep;
