//! The tests that hold ctxrace-nn's hand-written networks and acting policies to their candle
//! oracle (moved here from ctxrace-nn's own unit tests, which no longer have candle): one module
//! per module of ctxrace-nn.

mod dreamer_policy;
mod layer;
mod parameters;
mod rssm;
mod sac_policy;
mod weights;
