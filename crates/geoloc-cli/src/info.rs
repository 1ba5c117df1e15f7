//! `geoloc-rs info MAP`: what a map holds, after checking all of it (`Map::load` refuses a
//! corrupt, truncated or other-version file with the reason).

use std::fmt::Write as _;
use std::path::Path;

use geoloc_core::map::file::{FORMAT_NAME, FORMAT_VERSION};
use geoloc_core::map::{Map, MapHeader, MapNoise, RetrievalHeader, SelfCalibrationHeader};
use geoloc_core::stats::{EvenMedian, median};
use nalgebra::Matrix6;
use serde_json::Value;

/// Prints the summary of the map at `path` on stdout.
pub fn run(path: &Path) -> Result<(), String> {
    let bytes = std::fs::metadata(path).map_err(|e| format!("{}: {e}", path.display()))?.len();
    let (map, header) = Map::load(path).map_err(|e| e.to_string())?;
    print!("{}", summary(path, bytes, &map, &header));
    Ok(())
}

fn summary(path: &Path, bytes: u64, map: &Map, h: &MapHeader) -> String {
    let f = &h.frontend;
    let mut s = String::new();
    let _ = writeln!(s, "map               {}", path.display());
    let _ = writeln!(s, "file size         {bytes} bytes ({:.2} MiB)", bytes as f64 / (1024.0 * 1024.0));
    let _ = writeln!(s, "format            {FORMAT_NAME} version {FORMAT_VERSION}");
    let c = h.camera;
    let _ = writeln!(s, "camera            fx {} fy {} cx {} cy {}{}", c.fx, c.fy, c.cx, c.cy, image_size(f));
    let _ = writeln!(s, "camera estimate   {}", self_calibration(h));
    let labels = map.labels.as_ref().map_or_else(|| "as given (not adjusted)".to_string(), |l| l.summary());
    let _ = writeln!(s, "pose labels       {labels}");
    if let Some(l) = &map.labels {
        let _ = writeln!(s, "label_from_cam    {}", top_rows(&l.offset.matrix()));
    }
    let per = h.keypoints as f64 / h.keyframes.max(1) as f64;
    let _ = writeln!(s, "keyframes         {}", h.keyframes);
    let _ = writeln!(s, "keypoints         {} ({per:.1} per keyframe)", h.keypoints);
    let metric = if h.descriptor_kind == "binary" { "bytes, Hamming" } else { "floats, L2" };
    let _ = writeln!(s, "descriptors       {} ({} {metric})", h.descriptor_kind, h.descriptor_width);
    let _ = writeln!(s, "features          {}", features(f));
    let _ = writeln!(s, "retrieval         {}", retrieval(h));
    let _ = writeln!(s, "3D model          {}", model(map));
    let _ = writeln!(s, "pose covariances  {}", pose_covariances(map));
    let _ = writeln!(s, "map noise         {}", map_noise(&map.noise));
    if let Some(src) = f.get("source") {
        let frames = src.get("frames").and_then(Value::as_array).map_or(0, Vec::len);
        let name = src.get("sequence").and_then(Value::as_str).unwrap_or("?");
        let _ = writeln!(s, "built from        {name:?} ({frames} frames)");
    }
    let _ = writeln!(s, "frontend          {}", compact_frontend(f));
    s
}

/// The top 3×4 of a pose, row-major, rows separated by ";", every value as Rust's shortest
/// representation that reads back to the same f64 (the offset X with T_cam = T_label·X, which
/// the map applies: a robot converting poses itself needs it exactly).
fn top_rows(m: &nalgebra::Matrix4<f64>) -> String {
    let rows: Vec<String> =
        (0..3).map(|i| (0..4).map(|j| m[(i, j)].to_string()).collect::<Vec<_>>().join(" ")).collect();
    format!("[{}] (top 3×4, row-major; T_cam = T_label · label_from_cam)", rows.join("; "))
}

/// The 3D model's size; a model too small for the model locator to place a frame says so
/// (`geoloc-rs localize` refuses that locator on it).
fn model(map: &Map) -> String {
    let needed = geoloc_core::localizer::LocalizerOptions::default().min_correspondences;
    match map.model.as_ref().map(geoloc_core::map::SceneModel::len) {
        None => "none stored (the model locator builds it when it starts)".to_string(),
        Some(n) if n < needed => {
            format!("{n} points: too few for the model locator (a pose needs {needed}); use --locator paper")
        }
        Some(n) => format!("{n} points"),
    }
}

fn image_size(f: &Value) -> String {
    let cam = f.get("camera");
    let dim = |k: &str| cam.and_then(|c| c.get(k)).and_then(Value::as_u64);
    let dist = cam.and_then(|c| c.get("dist")).and_then(Value::as_array).filter(|d| !d.is_empty());
    match (dim("width"), dim("height")) {
        (Some(w), Some(h)) => {
            let d = dist.map_or("none".to_string(), |d| format!("{} coefficients", d.len()));
            format!(", {w}×{h} px, distortion {d} (keypoints are stored undistorted)")
        }
        _ => String::new(),
    }
}

/// What the map estimated about its camera (the localizer corrects every frame's keypoints with it).
/// The track residuals before → after: the median first (what the robust fit lowers), then
/// the RMS, which a few large residuals dominate and which may rise as the many fall.
fn self_calibration(h: &MapHeader) -> String {
    h.self_calibration
        .as_ref()
        .map_or_else(|| "none (the given intrinsics are used as they are)".to_string(), camera_estimate)
}

/// [`self_calibration`]'s line for a map that tried.
fn camera_estimate(sc: &SelfCalibrationHeader) -> String {
    let px = |v: Option<f64>| v.map_or("?".to_string(), |v| format!("{v:.3}"));
    match (&sc.camera, &sc.distortion) {
        (Some(c), Some(d)) => format!(
            "fx {:.2} fy {:.2} cx {:.2} cy {:.2}, distortion k1 {:+.5} k2 {:+.5} p1 {:+.6} p2 {:+.6}; \
             track residuals median {} -> {} px, rms {} -> {} px ({} observations); frames' keypoints are corrected with it",
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            d[0],
            d[1],
            d[2],
            d[3],
            px(sc.median_before_px),
            px(sc.median_after_px),
            px(sc.rms_before_px),
            px(sc.rms_after_px),
            sc.observations
        ),
        _ => format!("not applied ({})", sc.reason),
    }
}

fn features(f: &Value) -> String {
    match f.get("features") {
        Some(feat) => {
            let kind = feat.get("kind").and_then(Value::as_str).unwrap_or("?");
            let n = feat.get("n_features").map_or("?".to_string(), Value::to_string);
            let root = feat.get("root_sift").and_then(Value::as_bool).unwrap_or(false);
            format!("{kind}, {n} per image{}", if root { ", RootSIFT" } else { "" })
        }
        None => "not recorded (the map was not built by geoloc.Map.build)".to_string(),
    }
}

fn retrieval(h: &MapHeader) -> String {
    match &h.retrieval {
        RetrievalHeader::Bow { words } => format!("bag of words, {words} words (no network needed)"),
        RetrievalHeader::Global { dim } => {
            format!("global descriptor, {dim} values ({}): frames must carry one", network(h))
        }
        RetrievalHeader::Fused { words, dim } => format!(
            "bag of words ({words} words) and a {dim}-value global descriptor ({}), verified two-view: frames must carry one",
            network(h)
        ),
    }
}

/// The network the front end recorded: name and the start of its sha256.
fn network(h: &MapHeader) -> String {
    let net = h.frontend.get("retrieval");
    let name = net.and_then(|n| n.get("name")).and_then(Value::as_str).unwrap_or("?");
    let sha = net.and_then(|n| n.get("sha256")).and_then(Value::as_str).map_or("?", |s| &s[..s.len().min(12)]);
    format!("network {name:?}, sha256 {sha}…")
}

/// "no", or "yes" with the median position σ (m) and rotation σ (°) of the keyframes: the
/// root-mean diagonal of each 3×3 block (rotation σ is small, so its angle is σ itself).
fn pose_covariances(map: &Map) -> String {
    let Some(covs) = &map.pose_covariances else { return "no".to_string() };
    let median = |mut v: Vec<f64>| median(&mut v, EvenMedian::Upper).unwrap_or(f64::NAN);
    let sigma_p = median(covs.iter().map(|c| ((c[(0, 0)] + c[(1, 1)] + c[(2, 2)]) / 3.0).sqrt()).collect());
    let sigma_r = median(covs.iter().map(|c| ((c[(3, 3)] + c[(4, 4)] + c[(5, 5)]) / 3.0).sqrt()).collect());
    format!("yes (median σ position {:.4} m, rotation {:.3}°)", sigma_p, sigma_r.to_degrees())
}

/// C_map's per-axis σ (cm, °), then where it came from and the support it was measured at
/// ([`MapNoise::description`]): what the localizer adds to every covariance
/// ([`MapNoise::pose_covariance_at`]).
fn map_noise(n: &MapNoise) -> String {
    if n.pose_covariance == Matrix6::zeros() {
        return n.description();
    }
    let sigma = |a: usize| n.pose_covariance[(a, a)].max(0.0).sqrt();
    format!(
        "C_map σ position {:.1}/{:.1}/{:.1} cm, rotation {:.2}/{:.2}/{:.2}°, {}",
        100.0 * sigma(0),
        100.0 * sigma(1),
        100.0 * sigma(2),
        sigma(3).to_degrees(),
        sigma(4).to_degrees(),
        sigma(5).to_degrees(),
        n.description()
    )
}

/// The frontend JSON, with the list of source frames replaced by its length.
fn compact_frontend(f: &Value) -> String {
    let mut f = f.clone();
    if let Some(frames) = f.pointer_mut("/source/frames")
        && let Some(n) = frames.as_array().map(Vec::len)
    {
        *frames = Value::String(format!("<{n} frame indices>"));
    }
    f.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector6;

    #[test]
    fn the_camera_estimate_gives_the_median_residual_before_the_rms() {
        let sc: SelfCalibrationHeader = serde_json::from_str(
            r#"{"camera":{"fx":524.5,"fy":524.25,"cx":320.5,"cy":239.5},"distortion":[0.02,-0.08,-0.001,0.0004,0.0],
                "reason":"ok","rms_before_px":2.152,"rms_after_px":2.309,"median_before_px":1.024,"median_after_px":0.955,
                "observations":91556,"points":20000,"correction_sigma_px":0.13}"#,
        )
        .expect("valid header");
        let line = camera_estimate(&sc);
        assert!(
            line.contains("track residuals median 1.024 -> 0.955 px, rms 2.152 -> 2.309 px (91556 observations)"),
            "{line}"
        );
        let refused: SelfCalibrationHeader = serde_json::from_str(
            r#"{"reason":"too few tracks","rms_before_px":null,"rms_after_px":null,"median_before_px":null,
                "median_after_px":null,"observations":3,"points":1,"correction_sigma_px":null}"#,
        )
        .expect("valid header");
        assert_eq!(camera_estimate(&refused), "not applied (too few tracks)");
    }

    #[test]
    fn the_map_noise_line_says_sigma_source_and_support() {
        assert_eq!(map_noise(&MapNoise::default()), "none: not estimated, covariances are the measurement's alone");
        let deg = 1f64.to_radians();
        let c = Matrix6::from_diagonal(&Vector6::new(
            0.02f64.powi(2),
            0.01f64.powi(2),
            0.03f64.powi(2),
            deg * deg,
            0.0,
            0.0,
        ));
        let estimated =
            MapNoise { pose_covariance: c, holdout_samples: 40, holdout_inliers: 532.0, ..MapNoise::default() };
        assert_eq!(
            map_noise(&estimated),
            "C_map σ position 2.0/1.0/3.0 cm, rotation 1.00/0.00/0.00°, estimated from 40 held-out keyframes; \
             a pose on n < 532 inliers (their median) gets C_map·532/n"
        );
        let default = MapNoise { pose_covariance: c, holdout_samples: 3, ..MapNoise::default() };
        assert!(
            map_noise(&default)
                .ends_with("default: 3 held-out keyframes < 12 cannot estimate it (σ 2 cm / 1° per axis)")
        );
    }
}
