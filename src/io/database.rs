//! Reading a COLMAP SQLite database, strictly read-only, into an in-memory
//! snapshot the mapper works against.
//!
//! Schema facts (COLMAP 3.8, `PRAGMA user_version` 3800; newer versions 3900+):
//! * `cameras(camera_id, model, width, height, params f64 blob, prior_focal_length)`.
//! * `images(image_id, name, camera_id, [prior_qw..prior_tz in 3.8])`.
//! * `keypoints(image_id, rows, cols, data f32 blob)`, cols 2, 4 or 6, x y first;
//!   pixel centres at +0.5.
//! * `two_view_geometries(pair_id, rows, cols, data u32 pairs, config, F, E, H, ...)`:
//!   the verified inlier matches.
//! * `pair_id = 2147483647 * id1 + id2` with `id1 < id2` (see [`pair_id_to_image_ids`]).
//! * Newer versions add `pose_priors`, `rigs`, `rig_sensors`, `frames`, `frame_data`.
//!   The schema is detected from the tables and columns present.
use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::path::{Path, PathBuf};

use nalgebra::Vector2;
use rusqlite::types::ValueRef;
use rusqlite::{Connection, OpenFlags};

use crate::scene::camera::bad_image_size;
use crate::scene::correspondence_graph::CorrespondenceGraph;
use crate::scene::{Camera, CameraId, CameraModel, ImageId, Rigid3};

/// COLMAP's bound on image ids used in pair ids.
pub const MAX_NUM_IMAGES: u64 = 2_147_483_647;

/// `pair_id` for two image ids (order-independent, smaller id first).
pub fn image_ids_to_pair_id(a: ImageId, b: ImageId) -> u64 {
    let (lo, hi) = if a.0 <= b.0 { (a.0, b.0) } else { (b.0, a.0) };
    MAX_NUM_IMAGES * u64::from(lo) + u64::from(hi)
}

/// Inverse of [`image_ids_to_pair_id`]: `(id1, id2)` with `id1 < id2`.
pub fn pair_id_to_image_ids(pair_id: u64) -> (ImageId, ImageId) {
    let id2 = pair_id % MAX_NUM_IMAGES;
    let id1 = (pair_id - id2) / MAX_NUM_IMAGES;
    (ImageId(id1 as u32), ImageId(id2 as u32))
}

/// Why reading the database failed. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum DatabaseError {
    #[error("{path}: cannot open the database: {source}")]
    Open {
        path: PathBuf,
        source: rusqlite::Error,
    },
    #[error("{path}: not a SQLite database file")]
    NotSqlite { path: PathBuf },
    #[error("{path}: {what} (a COLMAP database file is expected, e.g. database.db)")]
    NotAFile { path: PathBuf, what: &'static str },
    #[error("{path}: the database is locked by another process (is COLMAP still writing it?)")]
    Locked { path: PathBuf },
    #[error("{path}: not a COLMAP database (missing tables: {missing})")]
    NotColmap { path: PathBuf, missing: String },
    #[error("{path}: table `{table}` is missing")]
    MissingTable { path: PathBuf, table: &'static str },
    #[error("{path}: table `{table}`, {row}: {detail}")]
    BadRow {
        path: PathBuf,
        table: &'static str,
        row: String,
        detail: String,
    },
    #[error("{path}: reading table `{table}`: {source}")]
    Sqlite {
        path: PathBuf,
        table: &'static str,
        source: rusqlite::Error,
    },
}

/// One image's row of the `images` table.
#[derive(Clone, Debug, PartialEq)]
pub struct DbImage {
    pub id: ImageId,
    pub name: String,
    pub camera_id: CameraId,
}

/// A pose prior stored in the database (3.8 `images.prior_*` columns or a
/// newer `pose_priors` table). Each part is present only if stored and finite.
#[derive(Clone, Debug, PartialEq)]
pub struct DbPosePrior {
    /// Prior position: in 3.8 the `prior_t*` of a row without a rotation
    /// (the feature extractor's EXIF GPS: latitude, longitude, altitude; a
    /// row with one is a `cam_from_world`), or `pose_priors`' position (in
    /// its `coordinate_system`).
    pub position: Option<[f64; 3]>,
    /// Prior `cam_from_world` (3.8 only; newer versions store no rotation).
    pub cam_from_world: Option<Rigid3>,
    /// COLMAP's coordinate system code (-1 undefined, 0 WGS84, 1 Cartesian), if stored.
    pub coordinate_system: Option<i64>,
}

/// COLMAP's coordinate system code of a GPS position (latitude and
/// longitude in degrees, altitude in metres).
pub const COORDINATE_SYSTEM_WGS84: i64 = 0;

impl DbPosePrior {
    /// A GPS position (latitude, longitude, altitude), not one in the map's frame.
    pub fn is_gps(&self) -> bool {
        self.coordinate_system == Some(COORDINATE_SYSTEM_WGS84)
    }
}

/// Latitude and longitude within their ranges and an altitude between the
/// Dead Sea's shore and a high flight (a 3.8 translation-only prior is
/// EXIF GPS; `map` checks that the positions are near the map).
fn is_geodetic(t: &[f64]) -> bool {
    t[0].abs() <= 90.0 && t[1].abs() <= 180.0 && (-1000.0..=20_000.0).contains(&t[2])
}

/// The verified geometry of an image pair (`two_view_geometries` row).
#[derive(Clone, Debug, PartialEq)]
pub struct TwoViewGeometry {
    pub image_id1: ImageId,
    pub image_id2: ImageId,
    /// COLMAP's configuration code (2 calibrated, 3 uncalibrated, 4 planar, ...).
    pub config: i64,
    /// Inlier matches: keypoint index in image 1, keypoint index in image 2.
    pub inlier_matches: Vec<[u32; 2]>,
    /// The fundamental matrix COLMAP estimated, row-major, in pixels
    /// (`x2^T F x1 = 0`), when the row has one (column `F`, 9 doubles, not
    /// all zero).
    pub fundamental: Option<[f64; 9]>,
    /// The essential matrix COLMAP estimated for a calibrated pair, row-major,
    /// in normalised camera coordinates (`x2^T E x1 = 0`, so
    /// `E = [t]x R` for `cam2_from_cam1 = (R, t)`), when the row has one
    /// (column `E`, 9 doubles, not all zero).
    pub essential: Option<[f64; 9]>,
}

/// What was found in the schema.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SchemaInfo {
    /// `PRAGMA user_version` (3800 for COLMAP 3.8, 3900 for 3.9-3.13).
    pub user_version: i64,
    pub tables: Vec<String>,
    /// Tables this reader does not know (reported, not read).
    pub unknown_tables: Vec<String>,
    /// Things present but not understood (reported, not read).
    pub notes: Vec<String>,
}

/// Everything the mapper needs from a database, read once.
#[derive(Clone, Debug, Default)]
pub struct DatabaseSnapshot {
    pub path: PathBuf,
    pub schema: SchemaInfo,
    pub cameras: BTreeMap<CameraId, Camera>,
    pub images: BTreeMap<ImageId, DbImage>,
    /// Keypoint positions per image in pixels (COLMAP convention, centres at +0.5).
    pub keypoints: BTreeMap<ImageId, Vec<Vector2<f64>>>,
    /// Verified pairs, ordered by pair id.
    pub two_view_geometries: Vec<TwoViewGeometry>,
    pub pose_priors: BTreeMap<ImageId, DbPosePrior>,
    /// Cameras whose focal length the database marks as a guess
    /// (`prior_focal_length = 0`: COLMAP's feature extractor found no focal
    /// length in the EXIF data nor on its command line and used 1.2 times the
    /// larger image side). The mapper self-calibrates these.
    pub cameras_without_focal_prior: BTreeSet<CameraId>,
}

impl DatabaseSnapshot {
    pub fn num_keypoints(&self, image: ImageId) -> usize {
        self.keypoints.get(&image).map_or(0, Vec::len)
    }

    pub fn image_by_name(&self, name: &str) -> Option<&DbImage> {
        self.images.values().find(|i| i.name == name)
    }

    /// The correspondence graph of the verified inlier matches.
    pub fn correspondence_graph(&self) -> CorrespondenceGraph {
        CorrespondenceGraph::new(
            self.images.keys().map(|&id| (id, self.num_keypoints(id))),
            self.two_view_geometries
                .iter()
                .map(|g| (g.image_id1, g.image_id2, g.inlier_matches.as_slice())),
        )
    }

    /// The database of only the images `keep`: their keypoints, the pairs
    /// between two of them and their pose priors; every camera stays (an
    /// unused one costs nothing).
    pub fn restricted_to(&self, keep: &BTreeSet<ImageId>) -> DatabaseSnapshot {
        fn kept<V: Clone>(
            map: &BTreeMap<ImageId, V>,
            keep: &BTreeSet<ImageId>,
        ) -> BTreeMap<ImageId, V> {
            map.iter()
                .filter(|(id, _)| keep.contains(id))
                .map(|(&id, v)| (id, v.clone()))
                .collect()
        }
        DatabaseSnapshot {
            path: self.path.clone(),
            schema: self.schema.clone(),
            cameras: self.cameras.clone(),
            images: kept(&self.images, keep),
            keypoints: kept(&self.keypoints, keep),
            two_view_geometries: self
                .two_view_geometries
                .iter()
                .filter(|g| keep.contains(&g.image_id1) && keep.contains(&g.image_id2))
                .cloned()
                .collect(),
            pose_priors: kept(&self.pose_priors, keep),
            cameras_without_focal_prior: self.cameras_without_focal_prior.clone(),
        }
    }
}

const KNOWN_TABLES: &[&str] = &[
    "cameras",
    "images",
    "keypoints",
    "descriptors",
    "matches",
    "two_view_geometries",
    "pose_priors",
    "rigs",
    "rig_sensors",
    "frames",
    "frame_data",
    "sqlite_sequence",
];

/// Opens `path` strictly read-only.
///
/// When no `-wal`/`-shm`/`-journal` file lies beside it (no process has it open), the
/// database is opened `immutable`, which reads without creating any file and
/// works on read-only files and folders. Otherwise it is opened `mode=ro`, which
/// sees the pending write-ahead log and reports locks.
fn open_read_only(path: &Path) -> Result<Connection, DatabaseError> {
    if !path.is_file() {
        let what = match std::fs::metadata(path) {
            Ok(meta) if meta.is_dir() => "is a folder",
            Ok(_) => "is not a regular file",
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => "does not exist",
            Err(_) => "cannot be read",
        };
        return Err(DatabaseError::NotAFile {
            path: path.to_owned(),
            what,
        });
    }
    let sibling = |suffix: &str| {
        let mut s = path.as_os_str().to_owned();
        s.push(suffix);
        PathBuf::from(s)
    };
    let live = [sibling("-wal"), sibling("-shm"), sibling("-journal")]
        .iter()
        .any(|p| p.exists());
    let abs = path.canonicalize().unwrap_or_else(|_| path.to_owned());
    let mut uri = String::from("file:");
    use std::os::unix::ffi::OsStrExt;
    for &b in abs.as_os_str().as_bytes() {
        // Percent-encode everything but unreserved ASCII and '/': SQLite decodes
        // %XX, so spaces, '?', '#', '%' and non-ASCII bytes all survive.
        if b.is_ascii_alphanumeric() || b"/-_.~".contains(&b) {
            uri.push(b as char);
        } else {
            uri.push_str(&format!("%{b:02X}"));
        }
    }
    uri.push_str(if live {
        "?mode=ro"
    } else {
        "?mode=ro&immutable=1"
    });
    let flags = OpenFlags::SQLITE_OPEN_READ_ONLY
        | OpenFlags::SQLITE_OPEN_URI
        | OpenFlags::SQLITE_OPEN_NO_MUTEX;
    let conn = Connection::open_with_flags(&uri, flags).map_err(|source| DatabaseError::Open {
        path: path.to_owned(),
        source,
    })?;
    conn.busy_timeout(std::time::Duration::from_millis(2000))
        .map_err(|source| DatabaseError::Open {
            path: path.to_owned(),
            source,
        })?;
    Ok(conn)
}

fn classify(path: &Path, table: &'static str, source: rusqlite::Error) -> DatabaseError {
    use rusqlite::ffi::ErrorCode;
    match source.sqlite_error_code() {
        Some(ErrorCode::NotADatabase) => DatabaseError::NotSqlite {
            path: path.to_owned(),
        },
        Some(ErrorCode::DatabaseBusy) | Some(ErrorCode::DatabaseLocked) => DatabaseError::Locked {
            path: path.to_owned(),
        },
        _ => DatabaseError::Sqlite {
            path: path.to_owned(),
            table,
            source,
        },
    }
}

struct Reader<'a> {
    path: &'a Path,
    conn: Connection,
}

impl Reader<'_> {
    fn bad_row(
        &self,
        table: &'static str,
        row: String,
        detail: impl fmt::Display,
    ) -> DatabaseError {
        DatabaseError::BadRow {
            path: self.path.to_owned(),
            table,
            row,
            detail: detail.to_string(),
        }
    }

    fn sql(&self, table: &'static str) -> impl Fn(rusqlite::Error) -> DatabaseError + '_ {
        move |e| classify(self.path, table, e)
    }

    fn columns(&self, table: &'static str) -> Result<Vec<String>, DatabaseError> {
        let mut stmt = self
            .conn
            .prepare(&format!("PRAGMA table_info(\"{table}\")"))
            .map_err(self.sql(table))?;
        let cols = stmt
            .query_map([], |row| row.get::<_, String>(1))
            .map_err(self.sql(table))?
            .collect::<Result<Vec<_>, _>>()
            .map_err(self.sql(table))?;
        Ok(cols)
    }

    fn schema(&self) -> Result<SchemaInfo, DatabaseError> {
        let user_version: i64 = self
            .conn
            .query_row("PRAGMA user_version", [], |r| r.get(0))
            .map_err(self.sql("sqlite_master"))?;
        let mut stmt = self
            .conn
            .prepare("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")
            .map_err(self.sql("sqlite_master"))?;
        let tables = stmt
            .query_map([], |row| row.get::<_, String>(0))
            .map_err(self.sql("sqlite_master"))?
            .collect::<Result<Vec<_>, _>>()
            .map_err(self.sql("sqlite_master"))?;
        let unknown_tables = tables
            .iter()
            .filter(|t| !KNOWN_TABLES.contains(&t.as_str()))
            .cloned()
            .collect();
        Ok(SchemaInfo {
            user_version,
            tables,
            unknown_tables,
            notes: Vec::new(),
        })
    }

    fn require(&self, schema: &SchemaInfo, table: &'static str) -> Result<(), DatabaseError> {
        if schema.tables.iter().any(|t| t == table) {
            Ok(())
        } else {
            Err(DatabaseError::MissingTable {
                path: self.path.to_owned(),
                table,
            })
        }
    }

    /// The cameras, and those whose focal length is a guess (a database
    /// without the `prior_focal_length` column has none: its intrinsics are
    /// taken as given).
    #[allow(clippy::type_complexity)]
    fn cameras(&self) -> Result<(BTreeMap<CameraId, Camera>, BTreeSet<CameraId>), DatabaseError> {
        const T: &str = "cameras";
        let prior_column = if self.columns(T)?.iter().any(|c| c == "prior_focal_length") {
            "prior_focal_length"
        } else {
            "1"
        };
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT camera_id, model, width, height, params, {prior_column} FROM cameras ORDER BY camera_id"
            ))
            .map_err(self.sql(T))?;
        let mut rows = stmt.query([]).map_err(self.sql(T))?;
        let mut cameras = BTreeMap::new();
        let mut without_prior = BTreeSet::new();
        while let Some(row) = rows.next().map_err(self.sql(T))? {
            let id: i64 = row.get(0).map_err(self.sql(T))?;
            let at = || format!("camera_id {id}");
            let model_id: i64 = row.get(1).map_err(self.sql(T))?;
            let width: i64 = row.get(2).map_err(self.sql(T))?;
            let height: i64 = row.get(3).map_err(self.sql(T))?;
            let blob: Option<Vec<u8>> = row.get(4).map_err(self.sql(T))?;
            // COLMAP writes 0 or 1; anything but 0 counts as a prior.
            let has_prior = !matches!(row.get_ref(5).map_err(self.sql(T))?, ValueRef::Integer(0));
            let camera_id =
                u32::try_from(id).map_err(|_| self.bad_row(T, at(), "camera id out of range"))?;
            let model = CameraModel::from_id(model_id).ok_or_else(|| {
                self.bad_row(T, at(), format!("unknown camera model id {model_id}"))
            })?;
            let blob = blob.unwrap_or_default();
            let expected = model.num_params() * 8;
            if blob.len() != expected {
                return Err(self.bad_row(
                    T,
                    at(),
                    format!(
                        "params blob has {} bytes, model {} needs {} f64 ({expected} bytes)",
                        blob.len(),
                        model.name(),
                        model.num_params()
                    ),
                ));
            }
            let params: Vec<f64> = blob
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("chunks of 8")))
                .collect();
            if params.iter().any(|p| !p.is_finite()) {
                return Err(self.bad_row(T, at(), "non-finite camera parameter"));
            }
            let (width, height) = match (u32::try_from(width), u32::try_from(height)) {
                (Ok(w), Ok(h)) => match bad_image_size(u64::from(w), u64::from(h)) {
                    None => (w, h),
                    Some(why) => return Err(self.bad_row(T, at(), why)),
                },
                _ => return Err(self.bad_row(T, at(), format!("bad image size {width}x{height}"))),
            };
            cameras.insert(
                CameraId(camera_id),
                Camera {
                    id: CameraId(camera_id),
                    model,
                    width,
                    height,
                    params,
                },
            );
            if !has_prior {
                without_prior.insert(CameraId(camera_id));
            }
        }
        Ok((cameras, without_prior))
    }

    fn images(
        &self,
        cameras: &BTreeMap<CameraId, Camera>,
        priors: &mut BTreeMap<ImageId, DbPosePrior>,
    ) -> Result<BTreeMap<ImageId, DbImage>, DatabaseError> {
        const T: &str = "images";
        let columns = self.columns(T)?;
        let prior_cols = [
            "prior_qw", "prior_qx", "prior_qy", "prior_qz", "prior_tx", "prior_ty", "prior_tz",
        ];
        let has_priors = prior_cols.iter().all(|c| columns.iter().any(|x| x == c));
        let sql = if has_priors {
            format!(
                "SELECT image_id, name, camera_id, {} FROM images ORDER BY image_id",
                prior_cols.join(", ")
            )
        } else {
            "SELECT image_id, name, camera_id FROM images ORDER BY image_id".to_owned()
        };
        let mut stmt = self.conn.prepare(&sql).map_err(self.sql(T))?;
        let mut rows = stmt.query([]).map_err(self.sql(T))?;
        let mut images = BTreeMap::new();
        while let Some(row) = rows.next().map_err(self.sql(T))? {
            let id: i64 = row.get(0).map_err(self.sql(T))?;
            let at = || format!("image_id {id}");
            let name: String = row.get(1).map_err(self.sql(T))?;
            let camera: i64 = row.get(2).map_err(self.sql(T))?;
            let image_id = match u32::try_from(id) {
                Ok(v) if u64::from(v) < MAX_NUM_IMAGES && v > 0 => ImageId(v),
                _ => return Err(self.bad_row(T, at(), "image id out of range")),
            };
            let camera_id = u32::try_from(camera).ok().map(CameraId);
            let camera_id = match camera_id {
                Some(c) if cameras.contains_key(&c) => c,
                _ => {
                    return Err(self.bad_row(
                        T,
                        format!("{} ({name})", at()),
                        format!("refers to camera_id {camera}, which is not in table `cameras`"),
                    ))
                }
            };
            if has_priors {
                let mut v = [f64::NAN; 7];
                for (k, slot) in v.iter_mut().enumerate() {
                    let x: Option<f64> = row.get(3 + k).map_err(self.sql(T))?;
                    *slot = x.unwrap_or(f64::NAN);
                }
                // The norm, not its square: 1e200 squared is infinite.
                let q_norm = v[..4].iter().fold(0.0f64, |n, x| n.hypot(*x));
                let q_ok = q_norm.is_finite() && q_norm > 1e-6;
                let t_ok = v[4..].iter().all(|x| x.is_finite());
                if q_ok || t_ok {
                    // COLMAP 3.8 writes a zero rotation and zero translation as
                    // "no prior"; treat an all-zero row as absent.
                    let all_zero_t = v[4..].iter().all(|x| *x == 0.0);
                    let prior = DbPosePrior {
                        position: None,
                        cam_from_world: (q_ok && t_ok && !all_zero_t).then(|| {
                            // Scaled first when huge: nalgebra's norm squares
                            // the parts (ordinary ones are passed as they are).
                            let q = [v[0], v[1], v[2], v[3]];
                            let q = if q_norm > 1e100 {
                                q.map(|x| x / q_norm)
                            } else {
                                q
                            };
                            Rigid3::from_colmap(q, [v[4], v[5], v[6]])
                        }),
                        coordinate_system: None,
                    };
                    if prior.cam_from_world.is_some() {
                        priors.insert(image_id, prior);
                    } else if !q_ok && t_ok && !all_zero_t && is_geodetic(&v[4..]) {
                        // COLMAP 3.8's feature extractor stores an image's
                        // EXIF GPS here: latitude, longitude (degrees) and
                        // altitude (metres), no rotation.
                        priors.insert(
                            image_id,
                            DbPosePrior {
                                position: Some([v[4], v[5], v[6]]),
                                cam_from_world: None,
                                coordinate_system: Some(COORDINATE_SYSTEM_WGS84),
                            },
                        );
                    }
                }
            }
            images.insert(
                image_id,
                DbImage {
                    id: image_id,
                    name,
                    camera_id,
                },
            );
        }
        Ok(images)
    }

    fn keypoints(
        &self,
        images: &BTreeMap<ImageId, DbImage>,
    ) -> Result<BTreeMap<ImageId, Vec<Vector2<f64>>>, DatabaseError> {
        const T: &str = "keypoints";
        let mut stmt = self
            .conn
            .prepare("SELECT image_id, rows, cols, data FROM keypoints ORDER BY image_id")
            .map_err(self.sql(T))?;
        let mut rows = stmt.query([]).map_err(self.sql(T))?;
        let mut out = BTreeMap::new();
        while let Some(row) = rows.next().map_err(self.sql(T))? {
            let id: i64 = row.get(0).map_err(self.sql(T))?;
            let at = || format!("image_id {id}");
            let n_rows: i64 = row.get(1).map_err(self.sql(T))?;
            let n_cols: i64 = row.get(2).map_err(self.sql(T))?;
            let blob: Option<Vec<u8>> = row.get(3).map_err(self.sql(T))?;
            let blob = blob.unwrap_or_default();
            let image_id = u32::try_from(id)
                .ok()
                .map(ImageId)
                .filter(|i| images.contains_key(i));
            let Some(image_id) = image_id else {
                return Err(self.bad_row(T, at(), "keypoints of an image not in table `images`"));
            };
            if n_rows < 0 || (n_rows > 0 && ![2, 4, 6].contains(&n_cols)) {
                return Err(self.bad_row(
                    T,
                    at(),
                    format!("unsupported keypoint layout rows={n_rows} cols={n_cols} (cols must be 2, 4 or 6)"),
                ));
            }
            // Checked: the row and column counts come from the file.
            let expected = (n_rows as u64)
                .checked_mul(n_cols.max(0) as u64)
                .and_then(|n| n.checked_mul(4));
            if expected != Some(blob.len() as u64) {
                let expected = expected.map_or("more than 2^64".to_owned(), |n| n.to_string());
                return Err(self.bad_row(
                    T,
                    at(),
                    format!(
                        "data blob has {} bytes but rows={n_rows} x cols={n_cols} float32 need {expected}",
                        blob.len()
                    ),
                ));
            }
            let stride = n_cols.max(1) as usize * 4;
            let mut points = Vec::with_capacity(n_rows as usize);
            for (k, rec) in blob.chunks_exact(stride).enumerate() {
                let x = f32::from_le_bytes(rec[0..4].try_into().expect("4 bytes"));
                let y = f32::from_le_bytes(rec[4..8].try_into().expect("4 bytes"));
                if !x.is_finite() || !y.is_finite() {
                    return Err(self.bad_row(T, at(), format!("keypoint {k} is not finite")));
                }
                points.push(Vector2::new(f64::from(x), f64::from(y)));
            }
            out.insert(image_id, points);
        }
        Ok(out)
    }

    fn two_view_geometries(
        &self,
        images: &BTreeMap<ImageId, DbImage>,
        keypoints: &BTreeMap<ImageId, Vec<Vector2<f64>>>,
    ) -> Result<Vec<TwoViewGeometry>, DatabaseError> {
        const T: &str = "two_view_geometries";
        let columns = self.columns(T)?;
        let column = |name: &'static str| {
            if columns.iter().any(|c| c == name) {
                name
            } else {
                "NULL"
            }
        };
        let (f_column, e_column) = (column("F"), column("E"));
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT pair_id, rows, cols, data, config, {f_column}, {e_column} FROM two_view_geometries ORDER BY pair_id"
            ))
            .map_err(self.sql(T))?;
        let mut rows = stmt.query([]).map_err(self.sql(T))?;
        let mut out = Vec::new();
        while let Some(row) = rows.next().map_err(self.sql(T))? {
            let pair_id: i64 = row.get(0).map_err(self.sql(T))?;
            let n_rows: i64 = row.get(1).map_err(self.sql(T))?;
            let n_cols: i64 = row.get(2).map_err(self.sql(T))?;
            let blob: Option<Vec<u8>> = row.get(3).map_err(self.sql(T))?;
            let config: i64 = row
                .get::<_, Option<i64>>(4)
                .map_err(self.sql(T))?
                .unwrap_or(0);
            let blob = blob.unwrap_or_default();
            // A matrix blob of another size or with non-finite values is not
            // used: F is only a hint for self-calibration, E only starts a
            // run from a rough pose.
            let matrix = |column: usize| {
                let blob: Option<Vec<u8>> = row.get(column).unwrap_or(None);
                blob.filter(|b| b.len() == 72).and_then(|b| {
                    let mut f = [0.0; 9];
                    for (v, c) in f.iter_mut().zip(b.chunks_exact(8)) {
                        *v = f64::from_le_bytes(c.try_into().expect("chunks of 8"));
                    }
                    (f.iter().all(|v| v.is_finite()) && f.iter().any(|v| *v != 0.0)).then_some(f)
                })
            };
            let (fundamental, essential) = (matrix(5), matrix(6));
            if pair_id < 0 {
                return Err(self.bad_row(T, format!("pair_id {pair_id}"), "negative pair id"));
            }
            let (id1, id2) = pair_id_to_image_ids(pair_id as u64);
            let at = || format!("pair_id {pair_id} (images {id1} and {id2})");
            for id in [id1, id2] {
                if !images.contains_key(&id) {
                    return Err(self.bad_row(
                        T,
                        at(),
                        format!("image {id} is not in table `images`"),
                    ));
                }
            }
            if n_rows == 0 {
                continue;
            }
            if n_rows < 0 || n_cols != 2 {
                return Err(self.bad_row(
                    T,
                    at(),
                    format!("unsupported match layout rows={n_rows} cols={n_cols}"),
                ));
            }
            let expected = (n_rows as u64).checked_mul(8);
            if expected != Some(blob.len() as u64) {
                let expected = expected.map_or("more than 2^64".to_owned(), |n| n.to_string());
                return Err(self.bad_row(
                    T,
                    at(),
                    format!(
                        "data blob has {} bytes but rows={n_rows} x 2 uint32 need {expected}",
                        blob.len()
                    ),
                ));
            }
            let (n1, n2) = (
                keypoints.get(&id1).map_or(0, Vec::len) as u64,
                keypoints.get(&id2).map_or(0, Vec::len) as u64,
            );
            let mut matches = Vec::with_capacity(n_rows as usize);
            for rec in blob.chunks_exact(8) {
                let a = u32::from_le_bytes(rec[0..4].try_into().expect("4 bytes"));
                let b = u32::from_le_bytes(rec[4..8].try_into().expect("4 bytes"));
                if u64::from(a) >= n1 || u64::from(b) >= n2 {
                    return Err(self.bad_row(
                        T,
                        at(),
                        format!("match ({a}, {b}) refers to a keypoint beyond the images' {n1} and {n2} keypoints"),
                    ));
                }
                matches.push([a, b]);
            }
            out.push(TwoViewGeometry {
                image_id1: id1,
                image_id2: id2,
                config,
                inlier_matches: matches,
                fundamental,
                essential,
            });
        }
        Ok(out)
    }

    /// Newer COLMAP's `pose_priors` table: read when keyed by image id, else reported.
    fn pose_priors_table(
        &self,
        schema: &mut SchemaInfo,
        images: &BTreeMap<ImageId, DbImage>,
        priors: &mut BTreeMap<ImageId, DbPosePrior>,
    ) -> Result<(), DatabaseError> {
        const T: &str = "pose_priors";
        if !schema.tables.iter().any(|t| t == T) {
            return Ok(());
        }
        let columns = self.columns(T)?;
        let has = |c: &str| columns.iter().any(|x| x == c);
        if !(has("image_id") && has("position")) {
            schema.notes.push(format!(
                "table `pose_priors` has a layout this version does not read (columns: {}); priors ignored",
                columns.join(", ")
            ));
            return Ok(());
        }
        let cs = if has("coordinate_system") {
            "coordinate_system"
        } else {
            "NULL"
        };
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT image_id, position, {cs} FROM pose_priors ORDER BY image_id"
            ))
            .map_err(self.sql(T))?;
        let mut rows = stmt.query([]).map_err(self.sql(T))?;
        while let Some(row) = rows.next().map_err(self.sql(T))? {
            let id: i64 = row.get(0).map_err(self.sql(T))?;
            let blob: Option<Vec<u8>> = row.get(1).map_err(self.sql(T))?;
            let coordinate_system: Option<i64> = row.get(2).map_err(self.sql(T))?;
            let Some(image_id) = u32::try_from(id)
                .ok()
                .map(ImageId)
                .filter(|i| images.contains_key(i))
            else {
                return Err(self.bad_row(
                    T,
                    format!("image_id {id}"),
                    "prior of an image not in table `images`",
                ));
            };
            let blob = blob.unwrap_or_default();
            if blob.len() != 24 {
                return Err(self.bad_row(
                    T,
                    format!("image_id {id}"),
                    format!(
                        "position blob has {} bytes, expected 3 f64 (24 bytes)",
                        blob.len()
                    ),
                ));
            }
            let p: Vec<f64> = blob
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect();
            if p.iter().all(|x| x.is_finite()) {
                let entry = priors.entry(image_id).or_insert(DbPosePrior {
                    position: None,
                    cam_from_world: None,
                    coordinate_system: None,
                });
                entry.position = Some([p[0], p[1], p[2]]);
                entry.coordinate_system = coordinate_system;
            }
        }
        Ok(())
    }
}

/// Reads the whole database at `path` (opened read-only; the file is never changed).
pub fn read_database(path: &Path) -> Result<DatabaseSnapshot, DatabaseError> {
    let conn = open_read_only(path)?;
    let reader = Reader { path, conn };
    let mut schema = reader.schema()?;
    let missing: Vec<&str> = ["cameras", "images"]
        .into_iter()
        .filter(|t| !schema.tables.iter().any(|x| x == t))
        .collect();
    if missing.len() == 2 {
        return Err(DatabaseError::NotColmap {
            path: path.to_owned(),
            missing: missing.join(", "),
        });
    }
    for table in ["cameras", "images", "keypoints", "two_view_geometries"] {
        reader.require(&schema, table)?;
    }
    for t in &schema.unknown_tables {
        schema
            .notes
            .push(format!("table `{t}` is not understood and was not read"));
    }
    let (cameras, cameras_without_focal_prior) = reader.cameras()?;
    let mut pose_priors = BTreeMap::new();
    let images = reader.images(&cameras, &mut pose_priors)?;
    let keypoints = reader.keypoints(&images)?;
    let two_view_geometries = reader.two_view_geometries(&images, &keypoints)?;
    reader.pose_priors_table(&mut schema, &images, &mut pose_priors)?;
    for t in ["rigs", "frames"] {
        if schema.tables.iter().any(|x| x == t) {
            schema.notes.push(format!(
                "table `{t}` (COLMAP 3.12+ rigs) is not used: every image is its own camera pose"
            ));
        }
    }
    Ok(DatabaseSnapshot {
        path: path.to_owned(),
        schema,
        cameras,
        images,
        keypoints,
        two_view_geometries,
        pose_priors,
        cameras_without_focal_prior,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pair_ids_round_trip() {
        for (a, b) in [(1u32, 2u32), (2, 1), (7, 2_000_000_000), (1, 1)] {
            let pid = image_ids_to_pair_id(ImageId(a), ImageId(b));
            let (x, y) = pair_id_to_image_ids(pid);
            assert_eq!((x.0, y.0), (a.min(b), a.max(b)));
        }
        // Hand-computed: 2147483647 * 1 + 2.
        assert_eq!(image_ids_to_pair_id(ImageId(1), ImageId(2)), 2_147_483_649);
    }
}
