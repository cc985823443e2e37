//! Several cars driven from outside (multi-agent races, PettingZoo's `ParallelEnv`): the ego
//! and the `agents - 1` rivals right ahead of it on the grid are agents, the others stay the
//! rivals `[rival] driver` names, scaled by the context as before.
//!
//! Each agent acts as the ego does (the same action mapping, observation and reward, from its
//! own car: its scan sees every other car, its rank counts every other car). An agent's episode
//! ends when it crashes (its car then stays where it stopped, an obstacle as a crashed ego is)
//! or drives backwards; the race ends for all when one agent completes the lap (the first past
//! the line wins), when every agent's episode has ended, or at the time limit (truncated). The
//! ego's launch (`ego_launch_below`) launches every agent.

use super::{reward, RaceEnv, RaceError, StepInfo};
use crate::vehicle::DT;

/// One agent's outcome of [`RaceEnv::step_agents`].
#[derive(Clone, Debug)]
pub struct AgentStep {
    /// Its LiDAR observation (zeros once its episode has ended).
    pub obs: Vec<f32>,
    /// Its reward (0 once its episode has ended before this step).
    pub reward: f64,
    /// Its episode ended (lap, crash, driving backwards, or another agent's lap).
    pub terminated: bool,
    /// The race hit the time limit.
    pub truncated: bool,
    /// Its details, as the ego's [`StepInfo`].
    pub info: StepInfo,
}

impl RaceEnv {
    /// Makes the ego and the `agents - 1` rivals behind the others agents, driven by
    /// [`RaceEnv::step_agents`] from the next [`RaceEnv::reset`] on; 1 (the default) is the
    /// single-agent race of [`RaceEnv::step`].
    pub fn set_agents(&mut self, agents: usize) -> Result<(), RaceError> {
        if agents == 0 || agents > self.cfg.rivals + 1 {
            return Err(RaceError::AgentCount {
                agents,
                rivals: self.cfg.rivals,
            });
        }
        self.agents = agents;
        self.finished = true;
        Ok(())
    }

    /// The cars driven from outside: the ego (car 0) and the rivals behind the others.
    pub fn agents(&self) -> usize {
        self.agents
    }

    /// Agent `i`'s observation now (after [`RaceEnv::reset`], the ego's is its return value).
    pub fn observe_agent(&mut self, i: usize) -> Vec<f32> {
        self.observe_car(i)
    }

    /// Advances one decision with each agent's action `a ∈ [-1, 1]²` (clipped; an agent whose
    /// episode has ended is ignored); returns every agent's outcome, in grid order.
    pub fn step_agents(&mut self, actions: &[[f64; 2]]) -> Result<Vec<AgentStep>, RaceError> {
        if self.finished {
            return Err(RaceError::Finished);
        }
        if actions.len() != self.agents {
            return Err(RaceError::Agents {
                agents: self.agents,
                actions: actions.len(),
            });
        }
        if let Some(bad) = actions.iter().find(|a| !a.iter().all(|v| v.is_finite())) {
            return Err(RaceError::BadAction(*bad));
        }
        let done: Vec<bool> = self.cars[..self.agents]
            .iter()
            .map(|c| c.crashed || c.retired)
            .collect();
        let commands: Vec<_> = actions
            .iter()
            .zip(&done)
            .map(|(&a, &d)| {
                if d {
                    (0.0, 0.0)
                } else {
                    self.cfg.action_to_command(a)
                }
            })
            .collect();
        self.advance(&commands);
        if let Some(e) = self.drivers.iter_mut().find_map(|d| d.take_error()) {
            self.finished = true;
            return Err(e.into());
        }
        let time = self.steps as f64 * self.cfg.physics_steps_per_action as f64 * DT;
        let mut outcomes: Vec<AgentStep> = (0..self.agents)
            .map(|i| self.agent_outcome(i, done[i], time))
            .collect();
        let lapped = outcomes.iter().any(|o| o.info.lap_complete);
        let all_done = self.cars[..self.agents]
            .iter()
            .all(|c| c.crashed || c.retired);
        let timed_out = self.steps >= self.max_steps;
        self.finished = lapped || all_done || timed_out;
        for (o, &was_done) in outcomes.iter_mut().zip(&done) {
            if was_done {
                continue;
            }
            o.terminated |= lapped || (timed_out && self.cfg.timeout_is_terminal);
            o.truncated = !o.terminated && timed_out;
        }
        // the race's metrics stay the ego's (car 0's), as in a single-agent race
        let (m, ego) = (&mut self.metrics, &outcomes[0]);
        m.steps = self.steps;
        m.progress = ego.info.progress.max(m.progress);
        if !done[0] {
            m.overtakes += ego.info.overtakes;
            m.a2a |= ego.info.a2a;
            m.wall_crash |= ego.info.wall_crash;
            m.reversed |= ego.info.reversed;
            m.episode_return += ego.reward;
            if ego.info.lap_complete {
                m.lap_time = Some(time);
            }
        }
        m.rivals_crashed = self.cars[1..].iter().filter(|c| c.crashed).count();
        Ok(outcomes)
    }

    /// Agent `i`'s outcome of the decision just driven (`was_done`: its episode had ended).
    fn agent_outcome(&mut self, i: usize, was_done: bool, time: f64) -> AgentStep {
        let length = self.track.length();
        let progress = (self.cars[i].travelled / length).clamp(0.0, 1.0);
        if was_done {
            return AgentStep {
                obs: vec![0.0; self.lidar.beams()],
                reward: 0.0,
                terminated: true,
                truncated: false,
                info: StepInfo {
                    progress,
                    time,
                    ..StepInfo::default()
                },
            };
        }
        let car = &self.cars[i];
        let proj = self.track.project(&car.vehicle.position(), Some(car.hint));
        let lap_complete = car.travelled >= length;
        let (wall_crash, a2a) = (car.wall_hit, car.car_hit);
        let reversed = !(car.crashed || lap_complete)
            && self
                .cfg
                .reverse_limit
                .is_some_and(|limit| car.travelled < car.furthest - limit);
        let rank = self.rank_of(i);
        let overtakes = self.ranks[i] as i32 - rank as i32;
        self.ranks[i] = rank;
        let reward = reward(
            &self.cfg,
            car.vehicle.speed(),
            car.vehicle.yaw() - proj.heading,
            proj.lateral,
            car.crashed || reversed,
            lap_complete,
            overtakes,
        );
        if reversed || lap_complete {
            self.cars[i].retired = true;
        }
        AgentStep {
            obs: self.observe_car(i),
            reward,
            terminated: self.cars[i].crashed || self.cars[i].retired,
            truncated: false,
            info: StepInfo {
                progress,
                overtakes,
                wall_crash,
                a2a,
                reversed,
                lap_complete,
                time,
            },
        }
    }
}
