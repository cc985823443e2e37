use crate::bridge::FromOracle;
use crate::testing::{assert_same_outputs, small_mlp, small_rssm};
use crate::{Mlp as CandleMlp, ParamStore, Rssm as CandleRssm};
use ctxrace_nn::parameters::{count, init, load_safetensors, to_safetensors};
use ctxrace_nn::{Activation, Mlp, Parameters, Rssm, Weights};

/// Networks built from [`Weights::initial`] and initialised from a seed are, to
/// the byte, the candle modules the same seed initialised (names, shapes, values: a seed
/// still gives the same run), and they save and load their weights.
#[test]
fn networks_initialised_in_place_are_the_candle_stores_to_the_byte() {
    let rssm_cfg = small_rssm(true);
    for act in [Activation::SiluNorm, Activation::Relu] {
        let shape = small_mlp(act);
        let store = ParamStore::new();
        CandleMlp::new(5, 7, 2, Some(3), act, store.builder().pp("encoder")).unwrap();
        CandleRssm::new(rssm_cfg, store.builder().pp("rssm")).unwrap();
        store.init(19).unwrap();
        let mut fresh = Weights::initial();
        let mut encoder = Mlp::from_weights(&mut fresh, "encoder.", &shape).unwrap();
        let mut rssm = Rssm::from_weights(&mut fresh, "rssm.", rssm_cfg).unwrap();
        fresh.finish().unwrap();
        let nets: &mut [&mut dyn Parameters] = &mut [&mut encoder, &mut rssm];
        init(nets, 19);
        let bytes = to_safetensors(nets).unwrap();
        assert_eq!(bytes, store.to_bytes().unwrap(), "{act:?}");
        assert_eq!(count(nets), store.count());
        init(nets, 20);
        assert_ne!(to_safetensors(nets).unwrap(), bytes);
        load_safetensors(nets, &bytes).unwrap();
        assert_eq!(to_safetensors(nets).unwrap(), bytes);
        // the forward pass reads the loaded weights (the transpose is refreshed)
        let copied = Mlp::from_oracle(
            &CandleMlp::new(5, 7, 2, Some(3), act, store.builder().pp("encoder")).unwrap(),
        )
        .unwrap();
        assert_same_outputs(&encoder, &copied, &format!("{act:?}"));
    }
}
