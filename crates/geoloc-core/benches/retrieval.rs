//! Criterion benchmarks of retrieval, matching and one localizer-sized query.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use geoloc_core::matching::{Descriptors, MatchOptions, match_descriptors};
use geoloc_core::parallel::{Parallelism, with_parallelism};
use geoloc_core::retrieval::{Backend, DescriptorIndex};
use geoloc_core::testing::SplitMix64;
use std::hint::black_box;

fn normalized(rng: &mut SplitMix64, n: usize, dim: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n * dim).map(|_| rng.normal() as f32).collect();
    for row in v.chunks_mut(dim) {
        let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt();
        row.iter_mut().for_each(|x| *x /= norm);
    }
    v
}

fn retrieval(c: &mut Criterion) {
    let mut g = c.benchmark_group("retrieval");
    g.sample_size(10);
    let mut rng = SplitMix64::new(1);
    for (n, dim) in [(20_000, 3), (20_000, 32), (20_000, 128)] {
        let data = normalized(&mut rng, n, dim);
        let queries = normalized(&mut rng, 2000, dim);
        let index = DescriptorIndex::new(data.clone(), dim).expect("valid");
        g.throughput(Throughput::Elements(2000));
        g.bench_function(format!("{n}x{dim}_2000q_{:?}", index.backend()), |b| {
            b.iter(|| index.query(black_box(&queries), 1))
        });
        if dim <= 8 {
            let flat = DescriptorIndex::with_backend(data, dim, Some(Backend::Flat)).expect("valid");
            g.bench_function(format!("{n}x{dim}_2000q_Flat"), |b| b.iter(|| flat.query(black_box(&queries), 1)));
        }
    }
    g.finish();
}

fn matching(c: &mut Criterion) {
    let mut g = c.benchmark_group("matching");
    g.sample_size(10);
    let mut rng = SplitMix64::new(2);
    let a: Vec<u8> = (0..2000 * 32).map(|_| (rng.next_u64() & 0xff) as u8).collect();
    let b: Vec<u8> = a.iter().map(|x| x ^ 1).collect();
    g.bench_function("binary_2000x2000", |bch| {
        bch.iter(|| {
            match_descriptors(
                &Descriptors::Binary { data: &a, width: 32 },
                &Descriptors::Binary { data: black_box(&b), width: 32 },
                &MatchOptions::default(),
            )
        })
    });
    // the same work on the calling thread (GEOLOC_PARALLELISM=false), for the speed-up
    g.bench_function("binary_2000x2000_sequential", |bch| {
        bch.iter(|| {
            with_parallelism(&Parallelism::Off, || {
                match_descriptors(
                    &Descriptors::Binary { data: &a, width: 32 },
                    &Descriptors::Binary { data: black_box(&b), width: 32 },
                    &MatchOptions::default(),
                )
            })
        })
    });
    let fa = normalized(&mut rng, 1000, 128);
    let fb: Vec<f32> = fa.iter().map(|x| x + 0.001).collect();
    g.bench_function("float_1000x1000x128", |bch| {
        bch.iter(|| {
            match_descriptors(
                &Descriptors::Float { data: &fa, width: 128 },
                &Descriptors::Float { data: black_box(&fb), width: 128 },
                &MatchOptions::default(),
            )
        })
    });
    g.finish();
}

criterion_group!(benches, retrieval, matching);
criterion_main!(benches);
