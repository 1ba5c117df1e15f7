//! Criterion benchmarks of the Lie-group primitives (single calls and 200k batches).

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use geoloc_core::lie::{SE3, SO3, Twist, se3, so3};
use geoloc_core::parallel::try_fill_items;
use geoloc_core::testing::SplitMix64;
use std::hint::black_box;

fn twists(n: usize) -> Vec<Twist> {
    let mut rng = SplitMix64::new(42);
    (0..n)
        .map(|_| {
            let angle = rng.uniform_in(0.0, std::f64::consts::PI);
            rng.twist(angle, 10.0)
        })
        .collect()
}

fn single_calls(c: &mut Criterion) {
    let xs = twists(1024);
    let poses: Vec<SE3> = xs.iter().map(SE3::exp).collect();
    let mut g = c.benchmark_group("single");
    g.throughput(Throughput::Elements(xs.len() as u64));
    // every output is passed whole to black_box so no part of the computation is elided
    g.bench_function("so3_exp", |b| {
        b.iter(|| {
            xs.iter().for_each(|x| {
                black_box(SO3::exp(&se3::phi(x)));
            })
        })
    });
    g.bench_function("so3_log", |b| {
        b.iter(|| {
            poses.iter().for_each(|t| {
                black_box(t.rotation.log());
            })
        })
    });
    g.bench_function("se3_exp", |b| {
        b.iter(|| {
            xs.iter().for_each(|x| {
                black_box(SE3::exp(black_box(x)));
            })
        })
    });
    g.bench_function("se3_log", |b| {
        b.iter(|| {
            poses.iter().for_each(|t| {
                black_box(t.log());
            })
        })
    });
    g.bench_function("so3_right_jacobian", |b| {
        b.iter(|| {
            xs.iter().for_each(|x| {
                black_box(so3::right_jacobian(&se3::phi(x)));
            })
        })
    });
    g.bench_function("se3_right_jacobian", |b| {
        b.iter(|| {
            xs.iter().for_each(|x| {
                black_box(se3::right_jacobian(x));
            })
        })
    });
    g.bench_function("se3_right_jacobian_inverse", |b| {
        b.iter(|| {
            xs.iter().for_each(|x| {
                black_box(se3::right_jacobian_inverse(x));
            })
        })
    });
    g.bench_function("se3_adjoint", |b| {
        b.iter(|| {
            poses.iter().for_each(|t| {
                black_box(t.adjoint());
            })
        })
    });
    g.bench_function("so3_from_matrix_checked", |b| {
        b.iter(|| {
            poses.iter().for_each(|t| {
                black_box(SO3::from_matrix(black_box(t.rotation.matrix())).ok());
            })
        })
    });
    g.finish();
}

/// 200k exps into a flat row-major buffer, as the Python binding does, with and without rayon.
fn batch_exp(c: &mut Criterion) {
    let n = 200_000;
    let xs = twists(n);
    let mut out = vec![0.0; n * 16];
    let mut g = c.benchmark_group("batch_200k");
    g.throughput(Throughput::Elements(n as u64));
    g.sample_size(20);
    let fill = |i: usize, item: &mut [f64]| {
        let m = SE3::exp(&xs[i]).matrix();
        for r in 0..4 {
            for col in 0..4 {
                item[4 * r + col] = m[(r, col)];
            }
        }
        Ok(())
    };
    g.bench_function("se3_exp_parallel", |b| b.iter(|| try_fill_items(&mut out, 16, fill)));
    g.bench_function("se3_exp_sequential", |b| {
        b.iter(|| out.chunks_mut(16).enumerate().try_for_each(|(i, item)| fill(i, item)))
    });
    g.finish();
}

criterion_group!(benches, single_calls, batch_exp);
criterion_main!(benches);
