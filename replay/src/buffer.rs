//! The replay ring buffer: one ring of steps per actor stream, sampled into sequence or
//! transition batches.
//!
//! Each actor's steps are stored in arrival order in its own ring (capacity / actors steps), so
//! a sequence is always contiguous steps of one actor. Steps carry a segment number that changes
//! wherever the stream is not contiguous (the actor's first chunk, chunks dropped on the way);
//! samples never span two segments. Sequences may span episodes, with `is_first` set only at
//! true episode starts (DreamerV3's convention); transitions never cross an episode end.
//!
//! [`ReplayBuffer::sample_sequences_paper_code`] draws sequences as the paper's code did instead
//! (cbdreamer `cbtools.sample_episodes`): episode by episode, with numpy's `RandomState(0)`.

use crate::numpy_rng::{ChoiceCdf, RandomState};
use ctxrace_config::{Batch, BatchSpec, Sampler, SequenceBatch, TransitionBatch};
use ctxrace_ipc::wire::step_stride;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Step flag: first step of an episode.
pub const FIRST: u8 = 1;
/// Step flag: the episode terminated here.
pub const TERMINAL: u8 = 2;
/// Step flag: the episode ended here (terminated or truncated).
pub const LAST: u8 = 4;
/// Step flag: the action before this step was chosen through a context mask (cMask).
pub const MASKED: u8 = 8;

/// Draws per requested sample before sampling gives up (data too fragmented).
const ATTEMPTS: usize = 64;

/// One actor's ring of steps.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Stream {
    /// Next slot to write.
    pub(crate) head: usize,
    /// Steps held.
    pub(crate) len: usize,
    /// Segment of the newest step.
    pub(crate) segment: u64,
    pub(crate) obs: Vec<f32>,
    pub(crate) action: Vec<f32>,
    pub(crate) reward: Vec<f32>,
    pub(crate) flags: Vec<u8>,
    pub(crate) context: Vec<f32>,
    pub(crate) mask: Vec<f32>,
    pub(crate) segments: Vec<u64>,
}

impl Stream {
    pub(crate) fn new(cap: usize, obs_dim: usize, act_dim: usize) -> Self {
        Self {
            head: 0,
            len: 0,
            segment: 0,
            obs: vec![0.0; cap * obs_dim],
            action: vec![0.0; cap * act_dim],
            reward: vec![0.0; cap],
            flags: vec![0; cap],
            context: vec![0.0; cap * 2],
            mask: vec![0.0; cap * 2],
            segments: vec![0; cap],
        }
    }

    pub(crate) fn cap(&self) -> usize {
        self.reward.len()
    }

    /// Slot of the `i`-th oldest step.
    pub(crate) fn slot(&self, i: usize) -> usize {
        (self.head + self.cap() - self.len + i) % self.cap()
    }
}

/// The replay's storage of actor steps.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayBuffer {
    pub(crate) obs_dim: usize,
    pub(crate) act_dim: usize,
    pub(crate) streams: Vec<Stream>,
    pub(crate) inserted: u64,
}

pub use ctxrace_config::replay::stream_capacity;

impl ReplayBuffer {
    /// A buffer of `capacity` steps split equally between `actors` streams.
    pub fn new(capacity: usize, actors: usize, obs_dim: usize, act_dim: usize) -> Self {
        let per = stream_capacity(capacity, actors);
        Self {
            obs_dim,
            act_dim,
            streams: (0..actors.max(1))
                .map(|_| Stream::new(per, obs_dim, act_dim))
                .collect(),
            inserted: 0,
        }
    }

    /// Observation size.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Action size.
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// Actor streams.
    pub fn actors(&self) -> usize {
        self.streams.len()
    }

    /// Steps it can hold.
    pub fn capacity(&self) -> usize {
        self.streams.iter().map(Stream::cap).sum()
    }

    /// The longest window of contiguous steps one sample can take: the largest actor's ring.
    pub fn longest_window(&self) -> usize {
        self.streams.iter().map(Stream::cap).max().unwrap_or(0)
    }

    /// Steps held.
    pub fn len(&self) -> usize {
        self.streams.iter().map(|s| s.len).sum()
    }

    /// Whether it holds no step.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Steps inserted since it was created (or since the snapshot's run started).
    pub fn inserted(&self) -> u64 {
        self.inserted
    }

    /// Appends a validated chunk payload (`steps x step_stride` floats, see
    /// [`ctxrace_ipc::wire`]) to `actor`'s stream; `after_gap` starts a new segment.
    /// The caller validated the actor id and the payload.
    pub fn insert_chunk(&mut self, actor: usize, payload: &[f32], after_gap: bool) {
        let (o, a) = (self.obs_dim, self.act_dim);
        let stride = step_stride(o, a);
        let s = &mut self.streams[actor];
        if after_gap {
            s.segment += 1;
        }
        let cap = s.cap();
        for step in payload.chunks_exact(stride) {
            let i = s.head;
            s.obs[i * o..(i + 1) * o].copy_from_slice(&step[..o]);
            s.action[i * a..(i + 1) * a].copy_from_slice(&step[o..o + a]);
            let rest = &step[o + a..];
            s.reward[i] = rest[0];
            s.flags[i] = ((rest[1] as u8) * FIRST)
                | ((rest[2] as u8) * TERMINAL)
                | ((rest[3] as u8) * LAST)
                | ((rest[4] as u8) * MASKED);
            s.context[i * 2..i * 2 + 2].copy_from_slice(&rest[5..7]);
            s.mask[i * 2..i * 2 + 2].copy_from_slice(&rest[7..9]);
            s.segments[i] = s.segment;
            s.head = (i + 1) % cap;
            s.len = (s.len + 1).min(cap);
            self.inserted += 1;
        }
    }

    /// One batch of `spec`: sequences drawn by `sampler`, transitions uniformly; `None` if the
    /// buffer cannot serve it yet.
    pub fn sample(&self, spec: BatchSpec, sampler: Sampler, rng: &mut ChaCha8Rng) -> Option<Batch> {
        match spec {
            BatchSpec::Sequence { batch, length } => self
                .sample_sequences_by(sampler, batch, length, rng)
                .map(Batch::Sequence),
            BatchSpec::Transition {
                batch,
                frames,
                reward_delay,
            } => self
                .sample_transitions(batch, frames, reward_delay, rng)
                .map(Batch::Transition),
        }
    }

    /// `batch` sequences of `length` steps drawn by `sampler` (the paper-code sampler does not
    /// use `rng`).
    pub fn sample_sequences_by(
        &self,
        sampler: Sampler,
        batch: usize,
        length: usize,
        rng: &mut ChaCha8Rng,
    ) -> Option<SequenceBatch> {
        match sampler {
            Sampler::Uniform => self.sample_sequences(batch, length, rng),
            Sampler::PaperCode => self.sample_sequences_paper_code(batch, length),
        }
    }

    /// Picks a stream with probability proportional to its steps usable for a window of `w`.
    fn pick_stream(&self, w: usize, rng: &mut ChaCha8Rng) -> Option<usize> {
        let weight = |s: &Stream| (s.len + 1).saturating_sub(w);
        let total: usize = self.streams.iter().map(weight).sum();
        if total == 0 {
            return None;
        }
        let mut u = rng.random_range(0..total);
        for (k, s) in self.streams.iter().enumerate() {
            let n = weight(s);
            if u < n {
                return Some(k);
            }
            u -= n;
        }
        None
    }

    /// An empty batch of `batch` sequences of `length` steps, its buffers reserved.
    fn sequence_batch(&self, batch: usize, length: usize) -> SequenceBatch {
        let (o, a) = (self.obs_dim, self.act_dim);
        let n = batch * length;
        SequenceBatch {
            batch,
            length,
            obs_dim: o,
            act_dim: a,
            obs: Vec::with_capacity(n * o),
            action: Vec::with_capacity(n * a),
            reward: Vec::with_capacity(n),
            is_first: Vec::with_capacity(n),
            is_terminal: Vec::with_capacity(n),
            context: Vec::with_capacity(n * 2),
            mask: Vec::with_capacity(n * 2),
            has_mask: Vec::with_capacity(n),
        }
    }

    /// Appends the step in slot `i` of `s` to `out`, its `is_first` set also where `first`.
    fn push_step(&self, out: &mut SequenceBatch, s: &Stream, i: usize, first: bool) {
        let (o, a) = (self.obs_dim, self.act_dim);
        out.obs.extend_from_slice(&s.obs[i * o..(i + 1) * o]);
        out.action.extend_from_slice(&s.action[i * a..(i + 1) * a]);
        out.reward.push(s.reward[i]);
        out.is_first
            .push(if first { 1.0 } else { flag(s.flags[i], FIRST) });
        out.is_terminal.push(flag(s.flags[i], TERMINAL));
        out.context.extend_from_slice(&s.context[i * 2..i * 2 + 2]);
        out.mask.extend_from_slice(&s.mask[i * 2..i * 2 + 2]);
        out.has_mask.push(flag(s.flags[i], MASKED));
    }

    /// `batch` sequences of `length` contiguous steps of one actor segment each; `None` if
    /// none could be found (too little or too fragmented data).
    pub fn sample_sequences(
        &self,
        batch: usize,
        length: usize,
        rng: &mut ChaCha8Rng,
    ) -> Option<SequenceBatch> {
        let mut out = self.sequence_batch(batch, length);
        for _ in 0..batch {
            let (k, start) = self.find(length, rng, |s, start| {
                s.segments[s.slot(start)] == s.segments[s.slot(start + length - 1)]
            })?;
            let s = &self.streams[k];
            for t in 0..length {
                self.push_step(&mut out, s, s.slot(start + t), false);
            }
        }
        Some(out)
    }

    /// The episodes held, stream by stream and oldest first: `(stream, first logical step,
    /// steps)`. An episode starts at a step flagged [`FIRST`], at a new segment, or at the
    /// oldest step held; the one still running is included with the steps it has so far.
    pub fn episodes(&self) -> Vec<(usize, usize, usize)> {
        let mut episodes = Vec::new();
        for (k, s) in self.streams.iter().enumerate() {
            let mut start = 0;
            for t in 1..=s.len {
                let ends = t == s.len || {
                    let (prev, i) = (s.slot(t - 1), s.slot(t));
                    s.flags[i] & FIRST != 0 || s.segments[i] != s.segments[prev]
                };
                if ends {
                    episodes.push((k, start, t - start));
                    start = t;
                }
            }
        }
        episodes
    }

    /// `batch` sequences of `length` steps drawn as the paper's code drew them (cbdreamer
    /// `cbtools.sample_episodes` under `from_generator`, c0fd903), from a fresh numpy
    /// `RandomState(0)`: each sequence starts in an episode chosen with probability
    /// proportional to its steps (`choice(p=)`), at `randint(0, steps − 1)` (never its last
    /// step); where the episode ends first, the sequence goes on from the first step of the
    /// next chosen episode. Episodes of fewer than 2 steps are chosen and passed over.
    /// `is_first` is set at the sequence's first step and at each join, besides true episode
    /// starts; `is_terminal` is as stored. The same buffer gives the same batch. `None` if no
    /// episode has 2 steps.
    pub fn sample_sequences_paper_code(
        &self,
        batch: usize,
        length: usize,
    ) -> Option<SequenceBatch> {
        let episodes = self.episodes();
        if episodes.iter().all(|&(_, _, n)| n < 2) {
            return None;
        }
        let steps: Vec<u64> = episodes.iter().map(|&(_, _, n)| n as u64).collect();
        let cdf = ChoiceCdf::new(&steps)?;
        let mut rs = RandomState::new(0);
        let mut out = self.sequence_batch(batch, length);
        for _ in 0..batch {
            let mut size = 0;
            while size < length {
                let (k, start, n) = episodes[rs.choice(&cdf)];
                if n < 2 {
                    continue;
                }
                let from = if size == 0 {
                    rs.randint(0, n as i64 - 1) as usize
                } else {
                    0
                };
                let take = (n - from).min(length - size);
                let s = &self.streams[k];
                for t in 0..take {
                    self.push_step(&mut out, s, s.slot(start + from + t), t == 0);
                }
                size += take;
            }
        }
        Some(out)
    }

    /// `batch` transitions `(o_t, a_t, r_{t+1+d}, o_{t+1}, terminal_{t+1+d}, c)` inside
    /// episodes, with `d = reward_delay` (0, or 1 for the paper's code's reward of the next
    /// action: then steps `t … t + 2` lie in one episode, and an episode's last action has no
    /// transition), observations stacking the last `frames` frames of the episode (oldest
    /// first, the episode's first frame repeated before its start); `None` if none could be
    /// found.
    pub fn sample_transitions(
        &self,
        batch: usize,
        frames: usize,
        reward_delay: usize,
        rng: &mut ChaCha8Rng,
    ) -> Option<TransitionBatch> {
        let (o, a) = (self.obs_dim, self.act_dim);
        let so = frames * o;
        let mut out = TransitionBatch {
            batch,
            obs_dim: so,
            act_dim: a,
            obs: Vec::with_capacity(batch * so),
            action: Vec::with_capacity(batch * a),
            reward: Vec::with_capacity(batch),
            next_obs: Vec::with_capacity(batch * so),
            terminal: Vec::with_capacity(batch),
            context: Vec::with_capacity(batch * 2),
        };
        for _ in 0..batch {
            let (k, t) = self.find(2 + reward_delay, rng, |s, t| {
                (t + 1..=t + 1 + reward_delay).all(|u| {
                    let (i, j) = (s.slot(u - 1), s.slot(u));
                    s.segments[i] == s.segments[j]
                        && s.flags[i] & LAST == 0
                        && s.flags[j] & FIRST == 0
                })
            })?;
            let s = &self.streams[k];
            let (j, late) = (s.slot(t + 1), s.slot(t + 1 + reward_delay));
            self.stack(s, t, frames, &mut out.obs);
            out.action.extend_from_slice(&s.action[j * a..(j + 1) * a]);
            out.reward.push(s.reward[late]);
            self.stack(s, t + 1, frames, &mut out.next_obs);
            out.terminal.push(flag(s.flags[late], TERMINAL));
            out.context.extend_from_slice(&s.context[j * 2..j * 2 + 2]);
        }
        Some(out)
    }

    /// Appends the `frames` frames ending at logical step `t`, walking back inside the episode
    /// (and segment) and repeating the earliest frame reached.
    fn stack(&self, s: &Stream, t: usize, frames: usize, out: &mut Vec<f32>) {
        let o = self.obs_dim;
        let mut idx = vec![t; frames];
        for f in (0..frames.saturating_sub(1)).rev() {
            let cur = idx[f + 1];
            let i = s.slot(cur);
            let back =
                cur > 0 && s.flags[i] & FIRST == 0 && s.segments[s.slot(cur - 1)] == s.segments[i];
            idx[f] = if back { cur - 1 } else { cur };
        }
        for t in idx {
            let i = s.slot(t);
            out.extend_from_slice(&s.obs[i * o..(i + 1) * o]);
        }
    }

    /// A uniformly drawn (stream, logical start) of a window of `w` steps satisfying `ok`.
    fn find(
        &self,
        w: usize,
        rng: &mut ChaCha8Rng,
        ok: impl Fn(&Stream, usize) -> bool,
    ) -> Option<(usize, usize)> {
        for _ in 0..ATTEMPTS {
            let k = self.pick_stream(w, rng)?;
            let s = &self.streams[k];
            let start = rng.random_range(0..=s.len - w);
            if ok(s, start) {
                return Some((k, start));
            }
        }
        None
    }
}

fn flag(flags: u8, bit: u8) -> f32 {
    if flags & bit != 0 {
        1.0
    } else {
        0.0
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A chunk payload of `obs_dim` 2, `act_dim` 1: obs = (actor, step value), action = step
    /// value, reward = step value; flags from `first`/`last` positions; the mask (0.25, 0.75)
    /// on every step but the first ones.
    pub(crate) fn payload(actor: f32, values: &[f32], first: &[usize], last: &[usize]) -> Vec<f32> {
        let mut p = Vec::new();
        for (k, &v) in values.iter().enumerate() {
            let is_first = first.contains(&k);
            let is_last = last.contains(&k);
            p.extend_from_slice(&[actor, v, v, v]);
            p.extend_from_slice(&[
                f32::from(u8::from(is_first)),
                f32::from(u8::from(is_last)),
                f32::from(u8::from(is_last)),
                f32::from(u8::from(!is_first)),
                0.5,
                -0.5,
                0.25,
                0.75,
            ]);
        }
        p
    }

    fn rng() -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(7)
    }

    #[test]
    fn ring_wraps_and_keeps_the_newest_steps() {
        let mut b = ReplayBuffer::new(10, 2, 2, 1);
        let values: Vec<f32> = (0..12).map(|v| v as f32).collect();
        b.insert_chunk(0, &payload(0.0, &values, &[0], &[]), true);
        assert_eq!(b.len(), 5);
        assert_eq!(b.inserted(), 12);
        let s = b.sample_sequences(20, 5, &mut rng()).unwrap();
        // Only actor 0 has data; the only window of 5 is steps 7..12, in order.
        for seq in s.reward.chunks(5) {
            assert_eq!(seq, &[7.0, 8.0, 9.0, 10.0, 11.0]);
        }
        assert!(b.sample_sequences(1, 6, &mut rng()).is_none());
    }

    #[test]
    fn sequences_stay_in_one_actor_and_segment() {
        let mut b = ReplayBuffer::new(200, 2, 2, 1);
        let a: Vec<f32> = (0..50).map(|v| v as f32).collect();
        let c: Vec<f32> = (100..150).map(|v| v as f32).collect();
        b.insert_chunk(0, &payload(0.0, &a[..25], &[0], &[]), true);
        b.insert_chunk(1, &payload(1.0, &c, &[0], &[]), true);
        // A gap in actor 0's stream: sequences must not span 24 -> 25.
        b.insert_chunk(0, &payload(0.0, &a[25..], &[], &[]), true);
        let s = b.sample_sequences(500, 4, &mut rng()).unwrap();
        let mut saw = [false; 2];
        for k in 0..500 {
            let obs = &s.obs[k * 8..(k + 1) * 8];
            let actor = obs[0];
            saw[actor as usize] = true;
            let vals: Vec<f32> = obs.chunks(2).map(|f| f[1]).collect();
            assert!(obs.chunks(2).all(|f| f[0] == actor), "mixed actors {obs:?}");
            assert!(vals.windows(2).all(|w| w[1] == w[0] + 1.0), "{vals:?}");
            assert!(
                !(vals[0] < 25.0 && vals[3] >= 25.0),
                "crossed a gap {vals:?}"
            );
        }
        assert_eq!(saw, [true, true]);
    }

    #[test]
    fn is_first_marks_only_true_episode_starts() {
        let mut b = ReplayBuffer::new(100, 1, 2, 1);
        let v: Vec<f32> = (0..10).map(|v| v as f32).collect();
        // Episodes: steps 0..=4 and 5..=9.
        b.insert_chunk(0, &payload(0.0, &v, &[0, 5], &[4, 9]), true);
        let s = b.sample_sequences(200, 3, &mut rng()).unwrap();
        for k in 0..200 {
            for t in 0..3 {
                let value = s.reward[k * 3 + t];
                let expect = if value == 0.0 || value == 5.0 {
                    1.0
                } else {
                    0.0
                };
                assert_eq!(s.is_first[k * 3 + t], expect, "step {value}");
                let term = if value == 4.0 || value == 9.0 {
                    1.0
                } else {
                    0.0
                };
                assert_eq!(s.is_terminal[k * 3 + t], term);
                let masked = 1.0 - expect;
                assert_eq!(s.has_mask[k * 3 + t], masked, "step {value}");
                assert_eq!(&s.mask[(k * 3 + t) * 2..(k * 3 + t + 1) * 2], &[0.25, 0.75]);
            }
        }
    }

    /// One stream of episodes of `lengths` steps whose step `r` of episode `e` holds the value
    /// `1000 e + r`; each episode terminates at its last step.
    fn episodes_buffer(lengths: &[usize]) -> ReplayBuffer {
        let mut b = ReplayBuffer::new(10_000, 1, 2, 1);
        for (e, &n) in lengths.iter().enumerate() {
            let values: Vec<f32> = (0..n).map(|r| (1000 * e + r) as f32).collect();
            b.insert_chunk(0, &payload(0.0, &values, &[0], &[n - 1]), e == 0);
        }
        b
    }

    /// The pieces `[episode, first step]` of each sampled sequence, split where `is_first` is set.
    fn pieces(s: &SequenceBatch) -> Vec<Vec<[usize; 2]>> {
        (0..s.batch)
            .map(|k| {
                let rows = k * s.length..(k + 1) * s.length;
                rows.filter(|&i| s.is_first[i] == 1.0)
                    .map(|i| {
                        let v = s.reward[i] as usize;
                        [v / 1000, v % 1000]
                    })
                    .collect()
            })
            .collect()
    }

    /// The expected pieces are what the paper's code (c0fd903, cbdreamer `cbtools.py`
    /// `sample_episodes` under `from_generator`) returned with numpy 2.4 on the same episode
    /// lengths: `[episode, first step]` of each part of each sequence.
    #[test]
    fn the_paper_code_sampler_draws_what_the_code_drew() {
        // (episode lengths, sequence length, the pieces of each sequence)
        type Case = (&'static [usize], usize, &'static [&'static [[usize; 2]]]);
        let cases: [Case; 3] = [
            (
                &[1, 1, 3, 1, 2, 1, 4],
                6,
                &[
                    &[[4, 0], [6, 0]],
                    &[[4, 0], [4, 0], [6, 0]],
                    &[[6, 2], [4, 0], [6, 0]],
                    &[[4, 0], [6, 0]],
                    &[[2, 0], [6, 0]],
                ],
            ),
            (
                &[5, 1, 12, 2, 30, 7],
                8,
                &[
                    &[[4, 21]],
                    &[[4, 27], [4, 0]],
                    &[[4, 21]],
                    &[[4, 23], [5, 0]],
                    &[[5, 2], [4, 0]],
                    &[[4, 14]],
                ],
            ),
            (
                &[5, 1, 12, 2, 30, 7, 3, 64, 2, 9],
                16,
                &[
                    &[[7, 53], [7, 0]],
                    &[[7, 39]],
                    &[[6, 1], [5, 0], [4, 0]],
                    &[[2, 10], [7, 0]],
                    &[[7, 46]],
                    &[[7, 37]],
                    &[[7, 8]],
                    &[[2, 3], [4, 0]],
                ],
            ),
        ];
        for (lengths, length, want) in cases {
            let b = episodes_buffer(lengths);
            let s = b.sample_sequences_paper_code(want.len(), length).unwrap();
            let got = pieces(&s);
            assert_eq!(got, want, "episodes of {lengths:?}");
            // every piece runs on inside its episode, one step at a time
            for k in 0..s.batch {
                for i in k * length + 1..(k + 1) * length {
                    if s.is_first[i] == 0.0 {
                        assert_eq!(s.reward[i], s.reward[i - 1] + 1.0);
                    }
                }
            }
            // the seed does not enter: another draw of the same buffer is the same batch
            assert_eq!(b.sample_sequences_paper_code(want.len(), length), Some(s));
        }
        assert!(episodes_buffer(&[1, 1])
            .sample_sequences_paper_code(2, 4)
            .is_none());
    }

    #[test]
    fn paper_code_sequences_crossing_an_episode_end_say_so() {
        // episodes of 3 and 4 steps: a sequence of 6 must cross from one into the next
        let b = episodes_buffer(&[3, 4]);
        let s = b.sample_sequences_paper_code(20, 6).unwrap();
        let mut crossed = 0;
        for k in 0..s.batch {
            let rows = k * 6..(k + 1) * 6;
            assert_eq!(s.is_first[rows.start], 1.0, "a sequence starts a state");
            for i in rows.clone().skip(1) {
                let (prev, now) = (s.reward[i - 1] as usize, s.reward[i] as usize);
                if now % 1000 == 0 {
                    // a join: the new episode starts a state, the one before ended (continue 0)
                    crossed += 1;
                    assert_eq!(s.is_first[i], 1.0);
                    assert_eq!(s.is_terminal[i - 1], 1.0, "{prev} -> {now}");
                    assert_eq!(s.has_mask[i], 0.0);
                } else {
                    assert_eq!((now, s.is_first[i]), (prev + 1, 0.0));
                    let last = [2, 1003].contains(&prev);
                    assert_eq!(s.is_terminal[i - 1], f32::from(u8::from(last)));
                }
            }
        }
        assert!(crossed >= s.batch, "every sequence crosses at least once");
        // the uniform sampler too may cross, but it leaves is_first to true starts
        let mut rng = rng();
        let u = b.sample(
            ctxrace_config::BatchSpec::Sequence {
                batch: 50,
                length: 6,
            },
            Sampler::Uniform,
            &mut rng,
        );
        let Some(Batch::Sequence(u)) = u else {
            panic!("no uniform batch")
        };
        for (v, f) in u.reward.iter().zip(&u.is_first) {
            assert_eq!(*f, f32::from(u8::from((*v as usize).is_multiple_of(1000))));
        }
    }

    #[test]
    fn transitions_stay_in_episodes_and_stack_frames() {
        let mut b = ReplayBuffer::new(100, 1, 2, 1);
        let v: Vec<f32> = (0..10).map(|v| v as f32).collect();
        b.insert_chunk(0, &payload(0.0, &v, &[0, 5], &[4, 9]), true);
        let t = b.sample_transitions(300, 3, 0, &mut rng()).unwrap();
        assert_eq!(t.obs_dim, 6);
        let mut saw_start = false;
        for k in 0..300 {
            let frames: Vec<f32> = t.obs[k * 6..(k + 1) * 6].chunks(2).map(|f| f[1]).collect();
            let next: Vec<f32> = t.next_obs[k * 6..(k + 1) * 6]
                .chunks(2)
                .map(|f| f[1])
                .collect();
            let cur = frames[2];
            assert_eq!(next[2], cur + 1.0);
            assert!(cur != 4.0 && cur != 9.0, "transition out of an episode end");
            assert_eq!(t.reward[k], cur + 1.0);
            assert_eq!(t.action[k], cur + 1.0);
            let start = if cur < 5.0 { 0.0 } else { 5.0 };
            let want: Vec<f32> = (0..3).map(|f| (cur - 2.0 + f as f32).max(start)).collect();
            assert_eq!(frames, want);
            saw_start |= cur == 0.0;
            let term = if next[2] == 4.0 || next[2] == 9.0 {
                1.0
            } else {
                0.0
            };
            assert_eq!(t.terminal[k], term);
        }
        assert!(saw_start);
        assert_eq!(&t.context[..2], &[0.5, -0.5]);
    }

    /// With `reward_delay = 1` (the paper's code's SAC buffer) a transition from `o_t` takes
    /// `a_t` and `o_{t+1}` but the reward and terminal flag of `t + 2`, and an episode's last
    /// action has no transition.
    #[test]
    fn a_reward_delay_pairs_each_action_with_the_next_ones_reward() {
        let mut b = ReplayBuffer::new(100, 1, 2, 1);
        let v: Vec<f32> = (0..10).map(|v| v as f32).collect();
        b.insert_chunk(0, &payload(0.0, &v, &[0, 5], &[4, 9]), true);
        let t = b.sample_transitions(300, 2, 1, &mut rng()).unwrap();
        let mut seen = [false; 10];
        for k in 0..300 {
            let cur = t.obs[k * 4 + 3];
            seen[cur as usize] = true;
            assert_eq!(t.next_obs[k * 4 + 3], cur + 1.0);
            assert_eq!(t.action[k], cur + 1.0);
            assert_eq!(t.reward[k], cur + 2.0, "from step {cur}");
            let term = f32::from(u8::from(cur + 2.0 == 4.0 || cur + 2.0 == 9.0));
            assert_eq!(t.terminal[k], term);
        }
        // steps 3 and 8 take the episode's last action; 4 and 9 end it
        assert_eq!(
            seen,
            [true, true, true, false, false, true, true, true, false, false]
        );
    }
}
