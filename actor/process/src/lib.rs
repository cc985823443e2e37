//! The ctxrace actor: experience collection on the simulator ([`ctxrace_sim`]) with a trained
//! agent's acting policy ([`collect`]), the ego driver that puts a trained agent or a reference
//! policy behind the simulator's [`ctxrace_sim::driver::Ego`] ([`driver`]), and the actor
//! process that sends its trajectories over shared memory ([`process`]).

pub mod collect;
pub mod driver;
pub mod process;
