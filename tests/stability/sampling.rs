//! Inverse-CDF sampling.

use proptest::prelude::*;
use radiance::engine::rng::Rng;
use radiance::engine::sampling::stratified::sample_pdf;

fn nasty_weight() -> impl Strategy<Value = f32> {
    prop_oneof![
        3 => Just(0.0f32),
        1 => Just(1e-30f32),
        1 => Just(1e-45f32),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(f32::NEG_INFINITY),
        1 => Just(-1.0f32),
        1 => Just(f32::MAX),
        1 => Just(1e38f32),
        4 => 0.0f32..1.0,
        2 => (-30.0f32..38.0).prop_map(|e| 10f32.powf(e)),
    ]
}

/// Sorted bin edges (coincident edges included).
fn bin_edges(bins: usize) -> impl Strategy<Value = Vec<f32>> {
    (
        -1e3f32..1e3,
        proptest::collection::vec(
            prop_oneof![1 => Just(0.0f32), 4 => (-6.0f32..3.0).prop_map(|e| 10f32.powf(e))],
            bins,
        ),
    )
        .prop_map(|(start, steps)| {
            let mut e = vec![start];
            for s in steps {
                let last = *e.last().unwrap();
                e.push(last + s);
            }
            e
        })
}

fn check_samples(edges: &[f32], out: &[f32], n: usize) {
    let (lo, hi) = (edges[0], edges[edges.len() - 1]);
    assert_eq!(out.len(), n);
    for &s in out {
        assert!(s.is_finite() && s >= lo && s <= hi, "sample {s} outside [{lo}, {hi}]");
    }
    assert!(out.windows(2).all(|p| p[0] <= p[1]), "not sorted: {out:?}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

    #[test]
    fn sample_pdf_is_sorted_finite_and_inside(
        (edges, weights) in (1usize..64).prop_flat_map(|b| (bin_edges(b), proptest::collection::vec(nasty_weight(), b))),
        n in 1usize..200,
        seed in proptest::option::of(any::<u64>()),
    ) {
        let mut rng = seed.map(Rng::new);
        let mut out = Vec::new();
        sample_pdf(&edges, &weights, n, rng.as_mut(), &mut out);
        check_samples(&edges, &out, n);
    }

    #[test]
    fn sample_pdf_all_zero_and_tiny_weights_are_uniform(
        bins in 1usize..64,
        tiny in prop_oneof![Just(0.0f32), Just(1e-45f32), Just(1e-30f32), Just(1e-12f32)],
        n in 64usize..256,
    ) {
        let edges: Vec<f32> = (0..=bins).map(|i| 2.0 + 4.0 * i as f32 / bins as f32).collect();
        let mut out = Vec::new();
        sample_pdf(&edges, &vec![tiny; bins], n, None, &mut out);
        check_samples(&edges, &out, n);
        // Uniform: the k-th sample sits at the k-th quantile of [2, 6].
        for (k, &s) in out.iter().enumerate() {
            let want = 2.0 + 4.0 * (k as f32 + 0.5) / n as f32;
            prop_assert!((s - want).abs() < 1e-3, "sample {k}: {s} vs {want}");
        }
    }

    #[test]
    fn sample_pdf_one_hot_concentrates_at_any_magnitude(
        bins in 2usize..64,
        hot in any::<prop::sample::Index>(),
        // a hot bin that dominates the 1e-5 padding of the others, up to f32::MAX
        magnitude in prop_oneof![Just(1.0f32), Just(0.5f32), Just(1e30f32), Just(1e38f32), Just(f32::MAX)],
        seed in any::<u64>(),
    ) {
        let hot = hot.index(bins);
        let edges: Vec<f32> = (0..=bins).map(|i| i as f32).collect();
        let mut w = vec![0.0f32; bins];
        w[hot] = magnitude;
        let mut out = Vec::new();
        sample_pdf(&edges, &w, 128, Some(&mut Rng::new(seed)), &mut out);
        check_samples(&edges, &out, 128);
        let inside = out.iter().filter(|&&s| s >= hot as f32 && s <= hot as f32 + 1.0).count();
        prop_assert!(inside >= 120, "{inside} of 128 samples in the hot bin {hot}");
        // Equal huge weights in every bin give the uniform density, as equal small ones do.
        let mut out = Vec::new();
        sample_pdf(&edges, &vec![magnitude; bins], 128, None, &mut out);
        check_samples(&edges, &out, 128);
        for (k, &s) in out.iter().enumerate() {
            let want = bins as f32 * (k as f32 + 0.5) / 128.0;
            prop_assert!((s - want).abs() < 1e-3 * bins as f32, "equal weights {magnitude}: sample {k} at {s}, want {want}");
        }
    }
}
