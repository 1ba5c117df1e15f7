//! Criterion benchmarks of the geometric locator: PnP refinement and RANSAC, triangulation.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use geoloc_core::camera::{Camera, project};
use geoloc_core::lie::{SE3, Twist};
use geoloc_core::pnp::{PnpOptions, solve_pnp};
use geoloc_core::testing::{SplitMix64, look_at};
use geoloc_core::triangulate::{TriangulationOptions, triangulate};
use nalgebra::{Vector2, Vector3};
use std::hint::black_box;

fn camera() -> Camera {
    Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid")
}

/// n points 2–8 m in front of a random camera, 1 px noise, a fraction of them replaced by
/// random pixels.
fn pnp_case(rng: &mut SplitMix64, n: usize, outliers: f64) -> (SE3, Vec<Vector3<f64>>, Vec<Vector2<f64>>) {
    let cam = camera();
    let pose = rng.pose(5.0);
    let mut points = Vec::with_capacity(n);
    let mut pixels = Vec::with_capacity(n);
    for _ in 0..n {
        let uv = Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0));
        let x = pose * (cam.unproject(&uv) * rng.uniform_in(2.0, 8.0));
        let mut obs = project(&cam, &pose, &x).uv + Vector2::new(rng.normal(), rng.normal());
        if rng.uniform() < outliers {
            obs = Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0));
        }
        points.push(x);
        pixels.push(obs);
    }
    (pose, points, pixels)
}

fn pnp(c: &mut Criterion) {
    let cam = camera();
    let options = PnpOptions::default();
    let mut g = c.benchmark_group("pnp");
    for n in [50, 200, 1000] {
        let mut rng = SplitMix64::new(n as u64);
        let (pose, points, pixels) = pnp_case(&mut rng, n, 0.0);
        let init = pose * SE3::exp(&Twist::new(0.01, -0.01, 0.01, 0.01, 0.005, -0.01));
        g.throughput(Throughput::Elements(n as u64));
        g.bench_function(format!("refine_{n}"), |b| {
            b.iter(|| solve_pnp(&cam, black_box(&points), &pixels, Some(&init), None, &options))
        });
        let (_, points, pixels) = pnp_case(&mut rng, n, 0.3);
        g.bench_function(format!("ransac_{n}_30pct"), |b| {
            b.iter(|| solve_pnp(&cam, black_box(&points), &pixels, None, None, &options))
        });
    }
    g.finish();
}

fn triangulation(c: &mut Criterion) {
    let cam = camera();
    let mut rng = SplitMix64::new(7);
    let focus = Vector3::new(0.0, 0.0, 5.0);
    let poses: Vec<SE3> = (0..7).map(|i| look_at(&Vector3::new(-1.0 + i as f64 / 3.0, 0.0, 0.0), &focus)).collect();
    let (mut cams, mut tracks, mut pixels) = (vec![], vec![], vec![]);
    for t in 0..2000 {
        let x = focus + Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(-1.5, 1.5));
        for (k, pose) in poses.iter().enumerate() {
            if rng.uniform() < 0.6 {
                let mut uv = project(&cam, pose, &x).uv + Vector2::new(rng.normal(), rng.normal());
                if rng.uniform() < 0.1 {
                    uv = Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0));
                }
                cams.push(k);
                tracks.push(t);
                pixels.push(uv);
            }
        }
    }
    let options = TriangulationOptions::default();
    let mut g = c.benchmark_group("triangulate");
    g.throughput(Throughput::Elements(2000));
    g.sample_size(30);
    g.bench_function("2000_tracks_10pct_outliers", |b| {
        b.iter(|| triangulate(&cam, &poses, None, &cams, &tracks, black_box(&pixels), &options))
    });
    g.finish();
}

criterion_group!(benches, pnp, triangulation);
criterion_main!(benches);
