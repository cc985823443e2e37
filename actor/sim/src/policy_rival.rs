//! A rival driven by a trained ctxrace agent, or by a policy trained elsewhere and saved as an MLP
//! file (`[rival] driver = "policy"`): every decision it
//! scans from its own pose with the race's LiDAR (the walls, the ego and the other rivals; the
//! race's range noise, drawn from the rival's own stream), and its agent acts on that scan and
//! the race's context `[c_v, c_θ]` exactly as it acted as the ego in training. Its action maps to
//! a command as the ego's does ([`RaceConfig::action_to_command`]); the context then scales the
//! speed by `1 + λ_v c_v`, as it scales the scripted rivals'. The agent steers unscaled: it reads
//! `c_θ` itself.
//!
//! The agent is read once, when the race is built ([`RivalAgent::load`]), and each rival keeps
//! its policy and its recurrent state; every episode restarts them, the sampling noise and the
//! scan noise seeded from the episode's seed and the rival's place on the grid, so that a race
//! replays from its seed.

use crate::collision::CarBox;
use crate::lidar::{Lidar, NearbyWalls};
use crate::vehicle::{idx, State};
use ctxrace_config::{Context, ContextGains, RaceConfig};
use ctxrace_nn::policy::mlp::{is_mlp_file, read_mlp_file};
use ctxrace_nn::policy::PolicyError;
use ctxrace_nn::Policy;
use ctxrace_run::trained::{CheckpointChoice, TrainedAgent, TrainedAgentError};
use ctxrace_tracks::Walls;
use nalgebra::Point2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

/// Why the rivals' agent could not be read or could not drive.
#[derive(Debug, thiserror::Error)]
pub enum RivalAgentError {
    /// `[rival] policy` names no readable trained agent.
    #[error("[rival] policy = {}", .path.display())]
    Load {
        /// The path configured.
        path: PathBuf,
        /// Why it could not be read.
        #[source]
        source: Box<TrainedAgentError>,
    },
    /// The agent's policy refuses the race's scan (another LiDAR) or its weights.
    #[error(
        "[rival] policy = {}: its agent cannot drive in this race (train it on a race with the \
         same [lidar] beams)",
        .path.display()
    )]
    Policy {
        /// The checkpoint read.
        path: PathBuf,
        /// The policy's error.
        #[source]
        source: Box<PolicyError>,
    },
}

/// The agent the rivals are, read once for a race: a trained ctxrace agent or a policy trained
/// elsewhere (an MLP file, [`ctxrace_nn::policy::mlp`]).
#[derive(Clone, Debug)]
pub enum RivalAgent {
    /// A trained agent's checkpoint.
    Trained(Box<TrainedAgent>),
    /// An MLP policy file and its bytes.
    Mlp(PathBuf, Vec<u8>),
}

impl RivalAgent {
    /// Reads the agent at `path`: an MLP policy file (`*.safetensors`), a run folder (its best
    /// checkpoint) or a checkpoint folder.
    pub fn load(path: &Path) -> Result<Self, RivalAgentError> {
        let failed = |source| RivalAgentError::Load {
            path: path.to_path_buf(),
            source: Box::new(source),
        };
        if is_mlp_file(path) {
            let bytes = read_mlp_file(path).map_err(|source| {
                failed(TrainedAgentError::Read {
                    path: path.to_path_buf(),
                    source,
                })
            })?;
            return Ok(Self::Mlp(path.to_path_buf(), bytes));
        }
        let trained = TrainedAgent::load(path, CheckpointChoice::Best).map_err(failed)?;
        Ok(Self::Trained(Box::new(trained)))
    }

    /// The checkpoint folder or the file the weights came from.
    pub fn checkpoint(&self) -> &Path {
        match self {
            Self::Trained(t) => &t.checkpoint,
            Self::Mlp(path, _) => path,
        }
    }

    /// Its acting policy for LiDAR frames of `beams` values.
    fn policy(&self, beams: usize) -> Result<Policy, PolicyError> {
        match self {
            Self::Trained(t) => Policy::new(&t.agent, beams, &t.weights, 0),
            Self::Mlp(_, bytes) => Policy::mlp(bytes, beams),
        }
    }
}

/// One rival's driver: its agent's policy, its scan and their noise.
pub struct PolicyRival {
    policy: Policy,
    /// The checkpoint, for error messages.
    checkpoint: PathBuf,
    deterministic: bool,
    lidar: Lidar,
    nearby: NearbyWalls,
    scan: Vec<f32>,
    /// The scan's range noise.
    noise: ChaCha8Rng,
    context: [f32; 2],
    /// `1 + λ_v c_v`.
    speed_scale: f64,
    /// The race's config: the action's mapping to a command.
    race: RaceConfig,
    /// The policy's error in the last decision, until the race takes it.
    error: Option<PolicyError>,
}

impl std::fmt::Debug for PolicyRival {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PolicyRival")
            .field("checkpoint", &self.checkpoint)
            .field("deterministic", &self.deterministic)
            .field("context", &self.context)
            .field("speed_scale", &self.speed_scale)
            .finish_non_exhaustive()
    }
}

impl PolicyRival {
    /// A rival of `race` driven by `agent`; refused when the agent cannot act on the race's
    /// scan (one decision on an empty scan is tried).
    pub fn new(agent: &RivalAgent, race: &RaceConfig) -> Result<Self, RivalAgentError> {
        let lidar = Lidar::new(&race.lidar);
        let checkpoint = agent.checkpoint().to_path_buf();
        let refused = |source| RivalAgentError::Policy {
            path: checkpoint.clone(),
            source: Box::new(source),
        };
        let mut policy = agent.policy(lidar.beams()).map_err(refused)?;
        let scan = vec![0.0; lidar.beams()];
        policy.act(&scan, [0.0; 2], true).map_err(refused)?;
        Ok(Self {
            policy,
            checkpoint,
            deterministic: race.rival.policy_deterministic,
            lidar,
            nearby: NearbyWalls::default(),
            scan,
            noise: ChaCha8Rng::seed_from_u64(0),
            context: [0.0; 2],
            speed_scale: 1.0,
            race: race.clone(),
            error: None,
        })
    }

    /// Starts an episode in `ctx` (gains `gains`) from the episode's `seed`, as rival `index`
    /// (0 the first ahead of the ego).
    pub fn restart(&mut self, gains: ContextGains, ctx: Context, seed: u64, index: usize) {
        // each rival its own streams, none shared with the ego's observation noise
        let own = seed ^ 0x9E37_79B9_7F4A_7C15u64.wrapping_mul(index as u64 + 1);
        self.policy.reset();
        self.policy.reseed(own);
        self.noise = ChaCha8Rng::seed_from_u64(own);
        self.noise.set_stream(1);
        self.context = [ctx.speed as f32, ctx.steer as f32];
        self.speed_scale = 1.0 + gains.lambda_v * ctx.speed;
        self.error = None;
    }

    /// The command `(steering angle, speed)` for the car in state `x` among `others` (every
    /// other car's box); a policy that fails stops the car and keeps its error for
    /// [`PolicyRival::take_error`].
    pub fn command(&mut self, walls: &Walls, others: &[CarBox], x: &State) -> (f64, f64) {
        let at = Point2::new(x[idx::X], x[idx::Y]);
        let (lidar, scan) = (&self.lidar, &mut self.scan);
        lidar.ranges(at, x[idx::YAW], &mut self.nearby, walls, others, scan);
        lidar.normalise(scan, &mut self.noise);
        match self.policy.act(scan, self.context, self.deterministic) {
            Ok(decision) => {
                let action = decision.action.map(f64::from);
                let (steer, speed) = self.race.action_to_command(action);
                (steer, speed * self.speed_scale)
            }
            Err(e) => {
                self.error = Some(e);
                (0.0, 0.0)
            }
        }
    }

    /// The error of a decision that failed since the last call, as a race error's message.
    pub fn take_error(&mut self) -> Option<RivalAgentError> {
        self.error.take().map(|source| RivalAgentError::Policy {
            path: self.checkpoint.clone(),
            source: Box::new(source),
        })
    }
}
