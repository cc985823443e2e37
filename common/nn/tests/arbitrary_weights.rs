//! Property test of the acting policy on arbitrary weight bytes: refused with an error, never a
//! panic.

use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Weights that passed their checksum may still be from another build or not weights at
    /// all: an actor refuses them with an error and keeps its policy.
    #[test]
    fn arbitrary_weights_are_refused_not_a_panic(
        bytes in prop_oneof![
            prop::collection::vec(any::<u8>(), 0..300),
            // a safetensors header length followed by junk
            (0u64..400, prop::collection::vec(any::<u8>(), 0..300)).prop_map(|(n, rest)| {
                let mut b = n.to_le_bytes().to_vec();
                b.extend(rest);
                b
            }),
        ],
        algo in prop_oneof![Just("sac"), Just("dreamerv3"), Just("cmask")],
    ) {
        let agent: ctxrace_config::AgentConfig =
            toml::from_str(&format!("algo = \"{algo}\"")).unwrap();
        prop_assert!(ctxrace_nn::Policy::new(&agent, 108, &bytes, 0).is_err());
    }
}
