//! Pictures of a race, for the command line (`ctxrace race --render`, `eval`'s and `train`'s
//! pictures) and the Python package's `render_mode="rgb_array"`: the track, the cars'
//! footprints and their trails coloured by speed, as a still, an animation, or one moment's RGB
//! frame ([`race`]); and what every figure shares, the embedded font and writing a drawing to
//! a file ([`figure`]). It links the simulator library alone, never the transport.

pub mod figure;
pub mod race;
