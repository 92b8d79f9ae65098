//! Bundle adjustment through Ceres (C++ in `cpp/`, bridged by cxx).
pub(crate) mod ffi;

/// Projects camera-frame points with the C++ camera model code used by the
/// solver. Exposed so tests and tools can check it against [`crate::scene::Camera::project`].
pub fn project_points_cpp(
    model_id: i32,
    params: &[f64],
    points_in_cam: &[[f64; 3]],
) -> Result<Vec<[f64; 2]>, String> {
    let flat: Vec<f64> = points_in_cam.iter().flatten().copied().collect();
    let mut pixels = vec![0.0; points_in_cam.len() * 2];
    ffi::ffi::project_points(model_id, params, &flat, &mut pixels)
        .map_err(|e| e.what().to_owned())?;
    Ok(pixels.chunks_exact(2).map(|p| [p[0], p[1]]).collect())
}
