//! Geodetic positions (GPS: latitude, longitude, height) in a map's frame.
//!
//! A georeferenced LiDAR map is in a projected coordinate reference system
//! (CRS), nearly always a transverse Mercator one (UTM zones, national
//! grids), often shifted by a constant so that its coordinates stay small;
//! a SLAM map may instead be a local east-north-up frame about a geodetic
//! origin. [`MapCrs`] takes a photo's GPS position (as COLMAP stores it
//! from the image's EXIF: degrees, and metres of height) into the map's
//! metres.
//!
//! The transverse Mercator projection is Krüger's series to the sixth
//! order in the third flattening (C. F. F. Karney, "Transverse Mercator
//! with an accuracy of a few nanometers", J. Geodesy 85, 2011), accurate
//! to well under a millimetre within a UTM zone. Datums are not
//! transformed: WGS84, ETRS89 and NAD83 differ by at most a couple of
//! metres, below what a photo's GPS gives.
use nalgebra::Vector3;

/// WGS84's semi-major axis, metres.
const WGS84_A: f64 = 6_378_137.0;
/// WGS84's flattening.
const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// GRS80's flattening (ETRS89, NAD83; the same semi-major axis).
const GRS80_F: f64 = 1.0 / 298.257_222_101;

/// A transverse Mercator projection: a UTM zone or a national grid.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct TransverseMercator {
    /// Latitude of origin and central meridian, degrees.
    pub lat0_deg: f64,
    pub lon0_deg: f64,
    /// Scale on the central meridian.
    pub k0: f64,
    /// False easting and northing, metres.
    pub false_easting: f64,
    pub false_northing: f64,
    /// The ellipsoid: semi-major axis (metres) and flattening.
    pub a: f64,
    pub f: f64,
}

impl TransverseMercator {
    /// UTM `zone` (1-60) on WGS84, north or south of the equator.
    pub fn utm(zone: u8, north: bool) -> Self {
        Self {
            lat0_deg: 0.0,
            lon0_deg: f64::from(zone) * 6.0 - 183.0,
            k0: 0.9996,
            false_easting: 500_000.0,
            false_northing: if north { 0.0 } else { 10_000_000.0 },
            a: WGS84_A,
            f: WGS84_F,
        }
    }

    /// Easting and northing (metres) of a latitude and longitude (degrees).
    pub fn forward(&self, lat_deg: f64, lon_deg: f64) -> (f64, f64) {
        let (x, y) = self.unscaled(lat_deg, lon_deg);
        let (_, y0) = self.unscaled(self.lat0_deg, self.lon0_deg);
        (
            self.false_easting + self.k0 * x,
            self.false_northing + self.k0 * (y - y0),
        )
    }

    /// The projection's easting and northing before the scale and the
    /// false origin (metres; the northing from the equator).
    fn unscaled(&self, lat_deg: f64, lon_deg: f64) -> (f64, f64) {
        let n = self.f / (2.0 - self.f);
        let (n2, n3) = (n * n, n * n * n);
        let (n4, n5, n6) = (n2 * n2, n2 * n3, n3 * n3);
        // The rectifying radius.
        let big_a = self.a / (1.0 + n) * (1.0 + n2 / 4.0 + n4 / 64.0 + n6 / 256.0);
        let alpha = [
            n / 2.0 - 2.0 / 3.0 * n2 + 5.0 / 16.0 * n3 + 41.0 / 180.0 * n4 - 127.0 / 288.0 * n5
                + 7891.0 / 37800.0 * n6,
            13.0 / 48.0 * n2 - 3.0 / 5.0 * n3 + 557.0 / 1440.0 * n4 + 281.0 / 630.0 * n5
                - 1983433.0 / 1935360.0 * n6,
            61.0 / 240.0 * n3 - 103.0 / 140.0 * n4
                + 15061.0 / 26880.0 * n5
                + 167603.0 / 181440.0 * n6,
            49561.0 / 161280.0 * n4 - 179.0 / 168.0 * n5 + 6601661.0 / 7257600.0 * n6,
            34729.0 / 80640.0 * n5 - 3418889.0 / 1995840.0 * n6,
            212378941.0 / 319334400.0 * n6,
        ];
        let phi = lat_deg.to_radians();
        let lambda = wrap_degrees(lon_deg - self.lon0_deg).to_radians();
        // The conformal latitude's tangent.
        let e = (self.f * (2.0 - self.f)).sqrt();
        let t = (phi.sin().atanh() - e * (e * phi.sin()).atanh()).sinh();
        let xi1 = t.atan2(lambda.cos());
        let eta1 = (lambda.sin() / (1.0 + t * t).sqrt()).atanh();
        let (mut xi, mut eta) = (xi1, eta1);
        for (j, a) in alpha.iter().enumerate() {
            let k = 2.0 * (j + 1) as f64;
            xi += a * (k * xi1).sin() * (k * eta1).cosh();
            eta += a * (k * xi1).cos() * (k * eta1).sinh();
        }
        (big_a * eta, big_a * xi)
    }

    /// Latitude and longitude (degrees) of an easting and northing, by
    /// Newton's method on [`Self::forward`] (to 1e-9 m).
    pub fn inverse(&self, easting: f64, northing: f64) -> (f64, f64) {
        let metres_per_deg = self.a * self.k0 * std::f64::consts::PI / 180.0;
        let mut lat = self.lat0_deg + (northing - self.false_northing) / metres_per_deg;
        let mut lon = self.lon0_deg;
        for _ in 0..30 {
            lat = lat.clamp(-89.9, 89.9);
            let (e, n) = self.forward(lat, lon);
            let (de, dn) = (easting - e, northing - n);
            if de.abs().max(dn.abs()) < 1e-9 {
                break;
            }
            let h = 1e-6;
            let (e_lat, n_lat) = self.forward(lat + h, lon);
            let (e_lon, n_lon) = self.forward(lat, lon + h);
            let j = nalgebra::Matrix2::new(
                (e_lat - e) / h,
                (e_lon - e) / h,
                (n_lat - n) / h,
                (n_lon - n) / h,
            );
            let Some(step) = j
                .try_inverse()
                .map(|ji| ji * nalgebra::Vector2::new(de, dn))
            else {
                break;
            };
            lat += step.x;
            lon += step.y;
        }
        (lat, lon)
    }
}

/// An angle in degrees wrapped to [-180, 180).
fn wrap_degrees(deg: f64) -> f64 {
    (deg + 180.0).rem_euclid(360.0) - 180.0
}

/// How the map's coordinates relate to latitude, longitude and height.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum CrsKind {
    /// A projected CRS: easting, northing, and the height as it is.
    TransverseMercator(TransverseMercator),
    /// East, north, up from a geodetic origin (WGS84), metres.
    Enu {
        lat_deg: f64,
        lon_deg: f64,
        height_m: f64,
    },
}

/// The map's coordinate reference system and the shift of its coordinates:
/// a map point is the CRS's coordinates minus `origin`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MapCrs {
    /// As given (`EPSG:32633`, `utm:33n`, `enu:LAT,LON,HEIGHT`).
    pub name: String,
    pub kind: CrsKind,
    /// The CRS's coordinates of the map's (0, 0, 0).
    pub origin: [f64; 3],
}

impl MapCrs {
    /// Parses `EPSG:CODE` (a transverse Mercator CRS: UTM zones on WGS84,
    /// ETRS89 or NAD83, national grids on those ellipsoids), `utm:ZONE[n|s]`
    /// (WGS84) or `enu:LAT,LON,HEIGHT`; the map's coordinates are the CRS's
    /// minus `origin`.
    pub fn parse(text: &str, origin: [f64; 3]) -> Result<Self, String> {
        let t = text.trim();
        let lower = t.to_ascii_lowercase();
        let kind = if let Some(code) = lower.strip_prefix("epsg:") {
            let code: u16 = code
                .trim()
                .parse()
                .map_err(|_| format!("`{t}`: an EPSG code is a number, e.g. EPSG:32633"))?;
            let def = crs_definitions::from_code(code)
                .ok_or_else(|| format!("`{t}`: EPSG:{code} is not a CRS this tool knows"))?;
            CrsKind::TransverseMercator(
                from_proj4(def.proj4).map_err(|e| format!("`{t}` ({}): {e}", def.proj4))?,
            )
        } else if let Some(zone) = lower.strip_prefix("utm:") {
            let zone = zone.trim();
            let (digits, north) = match zone.strip_suffix('s') {
                Some(d) => (d, false),
                None => (zone.strip_suffix('n').unwrap_or(zone), true),
            };
            let z: u8 = digits
                .parse()
                .ok()
                .filter(|z| (1..=60).contains(z))
                .ok_or_else(|| {
                    format!(
                        "`{t}`: a UTM zone is 1-60 with n (north, the default) or s, e.g. utm:33n"
                    )
                })?;
            CrsKind::TransverseMercator(TransverseMercator::utm(z, north))
        } else if let Some(rest) = lower.strip_prefix("enu:") {
            let v: Vec<f64> = rest
                .split(',')
                .map(|s| s.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|_| format!("`{t}`: expected enu:LAT,LON,HEIGHT (degrees, metres)"))?;
            match v.as_slice() {
                [lat, lon, h]
                    if (-90.0..=90.0).contains(lat)
                        && (-180.0..=180.0).contains(lon)
                        && h.is_finite() =>
                {
                    CrsKind::Enu {
                        lat_deg: *lat,
                        lon_deg: *lon,
                        height_m: *h,
                    }
                }
                _ => {
                    return Err(format!(
                        "`{t}`: expected enu:LAT,LON,HEIGHT (latitude within ±90, longitude within ±180 degrees, height in metres)"
                    ))
                }
            }
        } else {
            return Err(format!(
                "`{t}`: expected EPSG:CODE (e.g. EPSG:32633, UTM 33N), utm:ZONE (e.g. utm:33n) or enu:LAT,LON,HEIGHT"
            ));
        };
        if !origin.iter().all(|x| x.is_finite()) {
            return Err(format!("the map origin {origin:?} is not finite"));
        }
        Ok(Self {
            name: t.to_owned(),
            kind,
            origin,
        })
    }

    /// A GPS position (latitude and longitude in degrees, height in
    /// metres) in the map's frame.
    pub fn to_map(&self, lat_deg: f64, lon_deg: f64, height_m: f64) -> Vector3<f64> {
        let o = Vector3::from(self.origin);
        match self.kind {
            CrsKind::TransverseMercator(tm) => {
                let (e, n) = tm.forward(lat_deg, lon_deg);
                Vector3::new(e, n, height_m) - o
            }
            CrsKind::Enu {
                lat_deg: lat0,
                lon_deg: lon0,
                height_m: h0,
            } => {
                let d = ecef(lat_deg, lon_deg, height_m) - ecef(lat0, lon0, h0);
                let (sp, cp) = lat0.to_radians().sin_cos();
                let (sl, cl) = lon0.to_radians().sin_cos();
                let east = -sl * d.x + cl * d.y;
                let north = -sp * cl * d.x - sp * sl * d.y + cp * d.z;
                let up = cp * cl * d.x + cp * sl * d.y + sp * d.z;
                Vector3::new(east, north, up) - o
            }
        }
    }
}

/// Earth-centred, earth-fixed coordinates (WGS84, metres).
fn ecef(lat_deg: f64, lon_deg: f64, h: f64) -> Vector3<f64> {
    let e2 = WGS84_F * (2.0 - WGS84_F);
    let (sp, cp) = lat_deg.to_radians().sin_cos();
    let (sl, cl) = lon_deg.to_radians().sin_cos();
    let n = WGS84_A / (1.0 - e2 * sp * sp).sqrt();
    Vector3::new(
        (n + h) * cp * cl,
        (n + h) * cp * sl,
        (n * (1.0 - e2) + h) * sp,
    )
}

/// A transverse Mercator projection from a PROJ definition
/// (`+proj=utm +zone=33 ...` or `+proj=tmerc +lat_0=... +lon_0=...`), in
/// metres on WGS84 or GRS80.
fn from_proj4(proj4: &str) -> Result<TransverseMercator, String> {
    let value = |key: &str| -> Option<&str> {
        proj4.split_whitespace().find_map(|p| {
            let p = p.strip_prefix('+')?;
            match p.split_once('=') {
                Some((k, v)) if k == key => Some(v),
                None if p == key => Some(""),
                _ => None,
            }
        })
    };
    let number = |key: &str, default: f64| -> Result<f64, String> {
        value(key).map_or(Ok(default), |v| {
            v.parse()
                .map_err(|_| format!("its {key} `{v}` is not a number"))
        })
    };
    // Axes other than east-north (South Africa's Lo grids are west-south),
    // another prime meridian or a unit given by its size: not read.
    if let Some(axis) = value("axis").filter(|a| *a != "enu") {
        return Err(format!("its axes are `{axis}`, not east-north-up"));
    }
    if value("pm").is_some_and(|p| p != "greenwich" && p != "0") {
        return Err("its prime meridian is not Greenwich".to_owned());
    }
    if value("to_meter").is_some_and(|v| v.parse::<f64>() != Ok(1.0)) {
        return Err("its unit is not the metre (+to_meter)".to_owned());
    }
    match value("units") {
        None | Some("m") => {}
        Some(u) => {
            return Err(format!(
                "its unit is `{u}`; only CRSs in metres are read (convert the GPS positions yourself and give them as a pose file)"
            ))
        }
    }
    let f = match (value("ellps"), value("datum")) {
        (Some("WGS84"), _) | (_, Some("WGS84")) => WGS84_F,
        (Some("GRS80"), _) | (_, Some("NAD83")) => GRS80_F,
        (e, d) => {
            return Err(format!(
                "its ellipsoid ({}) is not WGS84 or GRS80: a datum shift from GPS would be needed",
                e.or(d).unwrap_or("unnamed")
            ))
        }
    };
    if value("towgs84").is_some_and(|v| v.split(',').any(|x| x.parse::<f64>() != Ok(0.0))) {
        return Err("its datum is shifted from WGS84 (+towgs84)".to_owned());
    }
    match value("proj") {
        Some("utm") => {
            let zone = number("zone", f64::NAN)?;
            if !(1.0..=60.0).contains(&zone) || zone.fract() != 0.0 {
                return Err("its UTM zone is missing or out of range".to_owned());
            }
            let mut tm = TransverseMercator::utm(zone as u8, value("south").is_none());
            tm.f = f;
            Ok(tm)
        }
        Some("tmerc") => Ok(TransverseMercator {
            lat0_deg: number("lat_0", 0.0)?,
            lon0_deg: number("lon_0", 0.0)?,
            k0: value("k_0").map_or_else(|| number("k", 1.0), |_| number("k_0", 1.0))?,
            false_easting: number("x_0", 0.0)?,
            false_northing: number("y_0", 0.0)?,
            a: WGS84_A,
            f,
        }),
        Some(p) => Err(format!(
            "its projection is `{p}`; only transverse Mercator ones (UTM, tmerc) are read"
        )),
        None => Err("it is not a projected CRS".to_owned()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eastings and northings computed by PROJ 9 (pyproj) from EPSG:4326.
    const PROJ: [(u16, f64, f64, f64, f64); 6] = [
        (32633, 39.7, 15.0, 500000.00000000134, 4394461.016987882),
        (
            32633,
            40.123456789,
            13.2,
            346625.2753633463,
            4443012.720225607,
        ),
        (
            32632,
            47.376887,
            8.541694,
            465402.8230277369,
            5247149.397355867,
        ),
        (
            32755,
            -33.8688,
            151.2093,
            889449.9970621977,
            6244409.977258302,
        ),
        (32631, 0.0, 3.0, 500000.000000001, 0.0),
        // 5 degrees outside its zone: the series still holds.
        (32633, 60.5, 10.2, 236476.38317062147, 6716712.912911989),
    ];

    #[test]
    fn utm_as_proj_computes_it() {
        for (code, lat, lon, e, n) in PROJ {
            let crs = MapCrs::parse(&format!("EPSG:{code}"), [0.0; 3]).expect("a UTM code");
            let p = crs.to_map(lat, lon, 12.5);
            assert!(
                (p.x - e).abs() < 1e-6 && (p.y - n).abs() < 1e-6,
                "EPSG:{code} ({lat}, {lon}): {p:?} against ({e}, {n})"
            );
            assert_eq!(p.z, 12.5);
            // The short spelling and the inverse.
            let zone = code % 100;
            let hemisphere = if code < 32700 { 'n' } else { 's' };
            let short = MapCrs::parse(&format!("utm:{zone}{hemisphere}"), [0.0; 3]).unwrap();
            assert_eq!(short.kind, crs.kind);
            let CrsKind::TransverseMercator(tm) = crs.kind else {
                unreachable!()
            };
            let (lat2, lon2) = tm.inverse(e, n);
            assert!((lat2 - lat).abs() < 1e-10 && (lon2 - lon).abs() < 1e-10);
        }
    }

    #[test]
    fn the_origin_is_subtracted() {
        let crs = MapCrs::parse("utm:33n", [500_000.0, 4_394_000.0, 200.0]).unwrap();
        let p = crs.to_map(39.7, 15.0, 210.0);
        assert!(
            (p - Vector3::new(0.0, 461.016987882, 10.0)).norm() < 1e-6,
            "{p:?}"
        );
    }

    #[test]
    fn national_grids_and_refusals() {
        // ETRS89 / UTM 32N (GRS80): within a millimetre of WGS84's zone here.
        let etrs = MapCrs::parse("EPSG:25832", [0.0; 3]).unwrap();
        let p = etrs.to_map(47.376887, 8.541694, 0.0);
        assert!((p.x - 465402.823).abs() < 1e-3 && (p.y - 5247149.397).abs() < 2e-3);
        // Gauss-Krüger zone 3 is on the Bessel ellipsoid: a datum shift.
        let err = MapCrs::parse("EPSG:31467", [0.0; 3]).unwrap_err();
        assert!(err.contains("datum") || err.contains("ellipsoid"), "{err}");
        // West-south axes (Lo 19), a unit by its size: refused.
        let axes = from_proj4(
            "+proj=tmerc +lat_0=0 +lon_0=19 +k=1 +x_0=0 +y_0=0 +axis=wsu +ellps=WGS84 +units=m",
        );
        assert!(axes.unwrap_err().contains("wsu"));
        let feet = from_proj4("+proj=tmerc +lon_0=19 +ellps=WGS84 +to_meter=0.3048");
        assert!(feet.unwrap_err().contains("to_meter"));
        // Geographic, Lambert, feet: refused with the reason.
        assert!(MapCrs::parse("EPSG:4326", [0.0; 3]).is_err());
        let lcc = MapCrs::parse("EPSG:2154", [0.0; 3]).unwrap_err();
        assert!(lcc.contains("lcc"), "{lcc}");
        for bad in [
            "utm:61",
            "utm:0n",
            "EPSG:abc",
            "enu:91,0,0",
            "enu:1,2",
            "mercator",
        ] {
            assert!(MapCrs::parse(bad, [0.0; 3]).is_err(), "{bad}");
        }
    }

    #[test]
    fn enu_is_east_north_up_about_its_origin() {
        let crs = MapCrs::parse("enu:47.376887,8.541694,408.5", [0.0; 3]).unwrap();
        assert!(crs.to_map(47.376887, 8.541694, 408.5).norm() < 1e-9);
        // 10 m up, and a small step north and east.
        let up = crs.to_map(47.376887, 8.541694, 418.5);
        assert!((up - Vector3::new(0.0, 0.0, 10.0)).norm() < 1e-6);
        let ne = crs.to_map(47.376887 + 1e-4, 8.541694 + 1e-4, 408.5);
        assert!(
            ne.x > 7.5 && ne.x < 7.6 && ne.y > 11.1 && ne.y < 11.2,
            "{ne:?}"
        );
        // The ECEF of the origin as PROJ computes it.
        let e = ecef(47.376887, 8.541694, 408.5);
        let proj = Vector3::new(4279229.260391484, 642718.9822874911, 4670540.267661153);
        assert!((e - proj).norm() < 1e-6);
    }
}
