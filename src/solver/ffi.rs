//! The cxx bridge to the C++ side (`cpp/`): camera projection (for cross-checks)
//! and the Ceres bundle-adjustment solve. Flat arrays in, flat arrays out.

#[cxx::bridge(namespace = "colmap_lidar")]
pub(crate) mod ffi {
    unsafe extern "C++" {
        include!("colmap-lidar/cpp/camera_bridge.h");

        /// Projects camera-frame points (xyz triples) with COLMAP model `model_id`
        /// and `params`, writing pixel pairs into `pixels` (NaN where the point
        /// cannot be projected). Errors on an unknown model or wrong sizes.
        fn project_points(
            model_id: i32,
            params: &[f64],
            points_in_cam: &[f64],
            pixels: &mut [f64],
        ) -> Result<()>;
    }
}
