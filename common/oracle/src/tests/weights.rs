use crate::ParamStore;
use ctxrace_nn::{Weights, WeightsError};

/// Two layers' parameters written by the candle store the learner keeps them in.
fn written() -> (ParamStore, Vec<u8>) {
    let store = ParamStore::new();
    let vb = store.builder();
    candle_nn::linear(3, 4, vb.pp("fc")).unwrap();
    candle_nn::layer_norm(4, 1e-3, vb.pp("ln")).unwrap();
    store.init(3).unwrap();
    let bytes = store.to_bytes().unwrap();
    (store, bytes)
}

#[test]
fn reads_every_tensor_the_candle_store_wrote() {
    let (store, bytes) = written();
    let mut weights = Weights::from_safetensors(&bytes).unwrap();
    for (name, var) in store.named() {
        let want: Vec<f32> = var.flatten_all().unwrap().to_vec1().unwrap();
        assert_eq!(weights.take(&name, var.dims()).unwrap(), want, "{name}");
    }
    weights.finish().unwrap();
}

#[test]
fn weights_of_another_network_are_errors_naming_the_tensor() {
    let (_, bytes) = written();
    let mut weights = Weights::from_safetensors(&bytes).unwrap();
    assert_eq!(
        weights.take("fc.weight", &[4, 5]),
        Err(WeightsError::Shape {
            name: "fc.weight".into(),
            found: vec![4, 3],
            want: vec![4, 5]
        })
    );
    assert_eq!(
        weights.take("fc.weight", &[4, 3]),
        Err(WeightsError::Missing("fc.weight".into()))
    );
    let err = weights.finish().unwrap_err().to_string();
    assert!(err.contains("fc.bias, ln.bias, ln.weight"), "{err}");
    assert!(matches!(
        Weights::from_safetensors(b"not safetensors"),
        Err(WeightsError::Format(_))
    ));
}
