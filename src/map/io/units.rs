//! The length unit of a point cloud's coordinates.
//!
//! PLY, PCD and E57 files name no unit (E57 is metres by its standard; the
//! others are read as metres). A LAS/LAZ file names its coordinate reference
//! system in a WKT record or in GeoTIFF keys, and surveys of the United States
//! are often in US survey feet. Every threshold of the tool is metric, so
//! coordinates in feet are converted to metres as they are read
//! ([`crate::map::io::read_point_cloud_with`] logs it), and longitude and
//! latitude in degrees are refused: no scale turns them into metres.
//! `--input-units` (of `map` and `prepare-map`) overrides what the file says.
use std::path::Path;

/// Metres in a US survey foot (1200/3937 m, EPSG unit 9003).
pub const US_SURVEY_FOOT_M: f64 = 1200.0 / 3937.0;
/// Metres in an international foot (EPSG unit 9002).
pub const FOOT_M: f64 = 0.3048;

/// A unit's size is taken as one metre when it is within this (relative).
const METRE_TOLERANCE: f64 = 1e-9;

/// WKT nesting deeper than this is refused (a real CRS nests under 10).
const MAX_WKT_DEPTH: usize = 64;

/// The length unit of the input's coordinates (`--input-units`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum InputUnits {
    /// As the file says: a LAS/LAZ file's coordinate reference system;
    /// metres for the other formats and for LAS files without one.
    #[default]
    Auto,
    Metre,
    /// The international foot, 0.3048 m.
    Foot,
    /// The US survey foot, 1200/3937 m.
    UsSurveyFoot,
}

impl InputUnits {
    /// Parses `auto`, `m`, `ft` or `us-ft` (and the units' spelled-out names).
    pub fn parse(text: &str) -> Result<Self, String> {
        match text.trim().to_ascii_lowercase().as_str() {
            "auto" => Ok(InputUnits::Auto),
            "m" | "metre" | "metres" | "meter" | "meters" => Ok(InputUnits::Metre),
            "ft" | "foot" | "feet" => Ok(InputUnits::Foot),
            "us-ft" | "us-foot" | "us-feet" | "us-survey-foot" | "us-survey-feet" => {
                Ok(InputUnits::UsSurveyFoot)
            }
            _ => Err(format!(
                "`{text}` is not a unit: auto (as the file says), m, ft (0.3048 m) or us-ft (1200/3937 m)"
            )),
        }
    }

    /// The unit given, or `None` for [`InputUnits::Auto`].
    pub fn unit(self) -> Option<LengthUnit> {
        match self {
            InputUnits::Auto => None,
            InputUnits::Metre => Some(LengthUnit::metre()),
            InputUnits::Foot => Some(LengthUnit::new("foot", FOOT_M)),
            InputUnits::UsSurveyFoot => Some(LengthUnit::new("US survey foot", US_SURVEY_FOOT_M)),
        }
    }
}

/// A length unit: its name and its size in metres.
#[derive(Clone, Debug, PartialEq)]
pub struct LengthUnit {
    pub name: String,
    pub metres: f64,
}

impl LengthUnit {
    fn new(name: &str, metres: f64) -> Self {
        LengthUnit {
            name: name.to_string(),
            metres,
        }
    }

    pub(crate) fn metre() -> Self {
        LengthUnit::new("metre", 1.0)
    }

    /// True for a unit of one metre.
    pub fn is_metre(&self) -> bool {
        (self.metres - 1.0).abs() <= METRE_TOLERANCE
    }
}

/// A file's coordinate units as its coordinate reference system gives them.
#[derive(Clone, Debug, PartialEq)]
pub enum CrsUnits {
    /// No CRS record, or one that names no length unit: metres are assumed.
    Unstated,
    /// The horizontal (x, y) and vertical (z) units, and where they were read.
    Linear {
        horizontal: LengthUnit,
        vertical: LengthUnit,
        source: String,
    },
    /// Longitude and latitude in degrees: the CRS's name and where it was read.
    Geographic { name: String, source: String },
}

/// The units of a LAS/LAZ file's coordinates, from its CRS records: the WKT
/// record first when the header says WKT (always for point formats 6-10),
/// else the GeoTIFF keys first; the other record when the first gives no
/// unit or cannot be read. An error is a record that cannot be read, or a
/// unit this reader cannot size, with no other record giving the unit (the
/// message says which).
pub fn las_units(header: &las::Header, path: &Path) -> Result<CrsUnits, String> {
    let wkt = header.get_wkt_crs_bytes().map(wkt_record_units);
    let geotiff = geotiff_record(header).map(|keys| keys.and_then(|k| geotiff_units(&k, path)));
    let records = if header.has_wkt_crs() {
        [wkt, geotiff]
    } else {
        [geotiff, wkt]
    };
    let mut error = None;
    for record in records.into_iter().flatten() {
        match record {
            Ok(CrsUnits::Unstated) => {}
            Ok(units) => return Ok(units),
            Err(e) => {
                error.get_or_insert(e);
            }
        }
    }
    error.map_or(Ok(CrsUnits::Unstated), Err)
}

/// The units of a WKT record's bytes (text up to the first NUL).
fn wkt_record_units(bytes: &[u8]) -> Result<CrsUnits, String> {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    let text = String::from_utf8_lossy(&bytes[..end]);
    parse_wkt(&text)
        .map(|root| wkt_units(&root))
        .map_err(|e| format!("its coordinate-system record (WKT) cannot be read: {e}"))
}

// ---------------------------------------------------------------- GeoTIFF keys

const GT_MODEL_TYPE: u16 = 1024;
const GEODETIC_CRS: u16 = 2048;
const GEOG_LINEAR_UNITS: u16 = 2052;
const GEOG_LINEAR_UNIT_SIZE: u16 = 2053;
const PROJECTED_CRS: u16 = 3072;
const PROJ_LINEAR_UNITS: u16 = 3076;
const PROJ_LINEAR_UNIT_SIZE: u16 = 3077;
const VERTICAL_CRS: u16 = 4096;
const VERTICAL_UNITS: u16 = 4099;
/// A GeoTIFF key value meaning "user-defined".
const USER_DEFINED: u16 = 32767;

/// The EPSG length units a GeoTIFF key may name.
fn epsg_length_unit(code: u16) -> Option<LengthUnit> {
    Some(match code {
        9001 => LengthUnit::metre(),
        9002 => LengthUnit::new("foot", FOOT_M),
        9003 => LengthUnit::new("US survey foot", US_SURVEY_FOOT_M),
        9005 => LengthUnit::new("Clarke's foot", 0.304_797_265_4),
        9036 => LengthUnit::new("kilometre", 1000.0),
        _ => return None,
    })
}

/// A GeoTIFF key: its id and its value, when stored in the key directory
/// itself (a short) or in the doubles record (its first double).
#[derive(Clone, Copy, Debug, PartialEq)]
struct GeoKey {
    id: u16,
    value: GeoValue,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum GeoValue {
    Short(u16),
    Double(f64),
    /// Text, or a value past the end of its record.
    Other,
}

/// The keys of the file's GeoTIFF key directory (`LASF_Projection` 34735),
/// `None` when it has none. Read here rather than through the `las` crate,
/// which refuses the whole directory for one bad entry (a citation's text
/// past the end of its record, say); only whole entries are read.
fn geotiff_record(header: &las::Header) -> Option<Result<Vec<GeoKey>, String>> {
    let record = |id: u16| {
        header
            .all_vlrs()
            .find(|v| v.user_id.eq_ignore_ascii_case("LASF_Projection") && v.record_id == id)
            .map(|v| v.data.as_slice())
    };
    let directory = record(34735)?;
    let shorts: Vec<u16> = directory
        .chunks_exact(2)
        .map(|b| u16::from_le_bytes([b[0], b[1]]))
        .collect();
    if shorts.len() < 4 {
        return Some(Err(format!(
            "its GeoTIFF key directory cannot be read: it holds {} bytes, less than its 8-byte header",
            directory.len()
        )));
    }
    let doubles: Vec<f64> = record(34736)
        .unwrap_or_default()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
        .collect();
    let keys = shorts[4..]
        .chunks_exact(4)
        .take(usize::from(shorts[3]))
        .map(|e| GeoKey {
            id: e[0],
            value: match e[1] {
                0 => GeoValue::Short(e[3]),
                34736 => doubles
                    .get(usize::from(e[3]))
                    .map_or(GeoValue::Other, |&d| GeoValue::Double(d)),
                _ => GeoValue::Other,
            },
        })
        .collect();
    Some(Ok(keys))
}

/// The units the GeoTIFF keys give (`path` names the file in a warning).
fn geotiff_units(keys: &[GeoKey], path: &Path) -> Result<CrsUnits, String> {
    let value = |id: u16| keys.iter().find(|k| k.id == id).map(|k| k.value);
    let short = |id: u16| match value(id) {
        Some(GeoValue::Short(v)) => Some(v),
        _ => None,
    };
    let double = |id: u16| match value(id) {
        Some(GeoValue::Double(v)) => Some(v),
        _ => None,
    };
    let source = "its GeoTIFF keys".to_string();
    // A unit key's unit; `size` is the key holding a user-defined unit's
    // size in metres, where GeoTIFF has one.
    let unit_key = |id: u16, size: Option<u16>| -> Result<Option<LengthUnit>, String> {
        match short(id) {
            None | Some(0) => Ok(None),
            Some(USER_DEFINED) => match size.and_then(double) {
                Some(m) if m.is_finite() && m > 0.0 => {
                    Ok(Some(LengthUnit::new("user-defined unit", m)))
                }
                _ => Err(format!(
                    "its GeoTIFF key {id} gives a user-defined length unit whose size it does not give"
                )),
            },
            Some(code) => epsg_length_unit(code).map(Some).ok_or_else(|| {
                format!(
                    "its GeoTIFF key {id} gives the length unit EPSG:{code}, which this reader does not \
                     size (it knows metre 9001, foot 9002, US survey foot 9003, Clarke's foot 9005, \
                     kilometre 9036)"
                )
            }),
        }
    };
    let model = short(GT_MODEL_TYPE);
    let projected = short(PROJECTED_CRS).filter(|&c| c != 0);
    let geodetic = short(GEODETIC_CRS).filter(|&c| c != 0);
    let crs_name =
        |code: Option<u16>| code.map_or_else(|| "unnamed".to_string(), |c| format!("EPSG:{c}"));
    if model == Some(2) || (model.is_none() && projected.is_none() && geodetic.is_some()) {
        return Ok(CrsUnits::Geographic {
            name: crs_name(geodetic),
            source,
        });
    }
    let horizontal = if model == Some(3) {
        unit_key(GEOG_LINEAR_UNITS, Some(GEOG_LINEAR_UNIT_SIZE))?
    } else {
        match unit_key(PROJ_LINEAR_UNITS, Some(PROJ_LINEAR_UNIT_SIZE))? {
            Some(unit) => Some(unit),
            None => match projected.filter(|&c| (1024..USER_DEFINED).contains(&c)) {
                Some(code) => match epsg_crs_unit(code)? {
                    EpsgCrsUnit::Linear(unit) => Some(unit),
                    EpsgCrsUnit::Geographic => {
                        return Ok(CrsUnits::Geographic {
                            name: format!("EPSG:{code}"),
                            source,
                        })
                    }
                    EpsgCrsUnit::Unknown => None,
                },
                None => None,
            },
        }
    };
    let vertical = match unit_key(VERTICAL_UNITS, None)? {
        Some(unit) => Some(unit),
        None => match short(VERTICAL_CRS).filter(|&c| c != 0) {
            Some(code) => match vertical_crs_unit(code) {
                Some(unit) => Some(unit),
                None => {
                    log::warn!(
                        "{}: its GeoTIFF keys give the vertical CRS EPSG:{code} and no vertical \
                         unit; heights are taken in the horizontal unit",
                        path.display()
                    );
                    None
                }
            },
            None => None,
        },
    };
    Ok(linear(horizontal, vertical, source))
}

/// The height unit of common vertical CRS codes (`crs-definitions` has no
/// vertical CRSs), for GeoTIFF keys that give a vertical CRS but no
/// vertical unit.
fn vertical_crs_unit(code: u16) -> Option<LengthUnit> {
    Some(match code {
        // NAVD88, NGVD29... in US survey feet; NAVD88 in feet.
        5702 | 6358 | 6360 => LengthUnit::new("US survey foot", US_SURVEY_FOOT_M),
        8228 => LengthUnit::new("foot", FOOT_M),
        // NAVD88, ODN, AHD, MSL, EGM96, EGM2008, NAP, DHHN92, DHHN2016,
        // Baltic 1977, NAVD88 depth: metres.
        3855 | 5701 | 5703 | 5705 | 5709 | 5711 | 5714 | 5773 | 5783 | 6357 | 7837 => {
            LengthUnit::metre()
        }
        _ => return None,
    })
}

/// The unit of an EPSG CRS code, from its PROJ definition.
enum EpsgCrsUnit {
    Linear(LengthUnit),
    Geographic,
    Unknown,
}

fn epsg_crs_unit(code: u16) -> Result<EpsgCrsUnit, String> {
    let Some(def) = crs_definitions::from_code(code) else {
        return Ok(EpsgCrsUnit::Unknown);
    };
    proj4_unit(def.proj4).map_err(|e| format!("its GeoTIFF keys name the CRS EPSG:{code}, {e}"))
}

/// The length unit of a PROJ definition (`+units=`, `+to_meter=`; metres
/// when neither is given), or geographic for `+proj=longlat`.
fn proj4_unit(proj4: &str) -> Result<EpsgCrsUnit, String> {
    let mut unit = LengthUnit::metre();
    for token in proj4.split_whitespace() {
        match token.split_once('=') {
            Some(("+proj", "longlat" | "latlong" | "lonlat" | "latlon")) => {
                return Ok(EpsgCrsUnit::Geographic)
            }
            Some(("+units", name)) => {
                unit = match name {
                    "m" => LengthUnit::metre(),
                    "km" => LengthUnit::new("kilometre", 1000.0),
                    "ft" => LengthUnit::new("foot", FOOT_M),
                    "us-ft" => LengthUnit::new("US survey foot", US_SURVEY_FOOT_M),
                    other => return Err(format!("whose unit `{other}` this reader does not size")),
                }
            }
            Some(("+to_meter", size)) => match size.parse::<f64>() {
                Ok(m) if m.is_finite() && m > 0.0 => unit = LengthUnit::new("unit", m),
                _ => return Err(format!("whose unit size `{size}` is not a number")),
            },
            _ => {}
        }
    }
    Ok(EpsgCrsUnit::Linear(unit))
}

/// The units found; a vertical unit not given is the horizontal one, a
/// horizontal one not given is the metre.
fn linear(
    horizontal: Option<LengthUnit>,
    vertical: Option<LengthUnit>,
    source: String,
) -> CrsUnits {
    match (horizontal, vertical) {
        (None, None) => CrsUnits::Unstated,
        (Some(h), None) => CrsUnits::Linear {
            vertical: h.clone(),
            horizontal: h,
            source,
        },
        (h, Some(v)) => CrsUnits::Linear {
            horizontal: h.unwrap_or_else(LengthUnit::metre),
            vertical: v,
            source,
        },
    }
}

// ------------------------------------------------------------------------- WKT

/// A WKT element: a keyword with its bracketed items, a quoted text, or a
/// bare word or number.
#[derive(Clone, Debug, PartialEq)]
enum Wkt {
    Node(WktNode),
    Text(String),
    Word(String),
}

#[derive(Clone, Debug, PartialEq)]
struct WktNode {
    /// Upper case.
    keyword: String,
    items: Vec<Wkt>,
}

impl WktNode {
    fn children(&self) -> impl Iterator<Item = &WktNode> {
        self.items.iter().filter_map(|i| match i {
            Wkt::Node(n) => Some(n),
            _ => None,
        })
    }

    fn child(&self, keywords: &[&str]) -> Option<&WktNode> {
        self.children()
            .find(|n| keywords.contains(&n.keyword.as_str()))
    }

    /// The first quoted text (a CRS's or a unit's name).
    fn name(&self) -> String {
        self.items
            .iter()
            .find_map(|i| match i {
                Wkt::Text(t) => Some(t.clone()),
                _ => None,
            })
            .unwrap_or_else(|| "unnamed".to_string())
    }
}

/// Parses WKT 1 or 2 (square brackets or parentheses; keywords in any case).
/// Several root elements separated by commas (ESRI's way of writing a
/// projected and a vertical CRS) are read as one compound CRS.
fn parse_wkt(text: &str) -> Result<WktNode, String> {
    let mut parser = WktParser {
        s: text.as_bytes(),
        i: 0,
    };
    let mut roots = Vec::new();
    loop {
        parser.skip_space();
        let word = parser.word();
        if word.is_empty() {
            return Err(format!("no keyword at byte {}", parser.i));
        }
        roots.push(parser.node(word, 0)?);
        parser.skip_space();
        match parser.peek() {
            None => break,
            Some(b',') => parser.i += 1,
            Some(_) => return Err(format!("text after the end, at byte {}", parser.i)),
        }
    }
    Ok(if roots.len() == 1 {
        roots.remove(0)
    } else {
        WktNode {
            keyword: "COMPD_CS".to_string(),
            items: roots.into_iter().map(Wkt::Node).collect(),
        }
    })
}

struct WktParser<'a> {
    s: &'a [u8],
    i: usize,
}

impl WktParser<'_> {
    fn peek(&self) -> Option<u8> {
        self.s.get(self.i).copied()
    }

    fn skip_space(&mut self) {
        while self.peek().is_some_and(|c| c.is_ascii_whitespace()) {
            self.i += 1;
        }
    }

    /// A bare word or number (anything up to a delimiter).
    fn word(&mut self) -> String {
        let start = self.i;
        while self
            .peek()
            .is_some_and(|c| !c.is_ascii_whitespace() && !b",[]()\"".contains(&c))
        {
            self.i += 1;
        }
        String::from_utf8_lossy(&self.s[start..self.i]).into_owned()
    }

    /// The bracketed items after `keyword`.
    fn node(&mut self, keyword: String, depth: usize) -> Result<WktNode, String> {
        if depth > MAX_WKT_DEPTH {
            return Err(format!("nested deeper than {MAX_WKT_DEPTH}"));
        }
        self.skip_space();
        let close = match self.peek() {
            Some(b'[') => b']',
            Some(b'(') => b')',
            _ => {
                return Err(format!(
                    "`{keyword}` is not followed by `[`, at byte {}",
                    self.i
                ))
            }
        };
        self.i += 1;
        let mut items = Vec::new();
        loop {
            self.skip_space();
            match self.peek() {
                Some(c) if c == close && items.is_empty() => {
                    self.i += 1;
                    break;
                }
                Some(b'"') => items.push(Wkt::Text(self.text()?)),
                Some(_) => {
                    let word = self.word();
                    if word.is_empty() {
                        return Err(format!("an empty item at byte {}", self.i));
                    }
                    self.skip_space();
                    if matches!(self.peek(), Some(b'[' | b'(')) {
                        items.push(Wkt::Node(self.node(word, depth + 1)?));
                    } else {
                        items.push(Wkt::Word(word));
                    }
                }
                None => return Err(format!("`{keyword}` is not closed")),
            }
            self.skip_space();
            match self.peek() {
                Some(b',') => self.i += 1,
                Some(c) if c == close => {
                    self.i += 1;
                    break;
                }
                _ => return Err(format!("`{keyword}` is not closed, at byte {}", self.i)),
            }
        }
        Ok(WktNode {
            keyword: keyword.to_ascii_uppercase(),
            items,
        })
    }

    /// A quoted text (`""` inside is one quote).
    fn text(&mut self) -> Result<String, String> {
        let start = self.i;
        self.i += 1;
        let mut out = Vec::new();
        loop {
            match self.peek() {
                Some(b'"') if self.s.get(self.i + 1) == Some(&b'"') => {
                    out.push(b'"');
                    self.i += 2;
                }
                Some(b'"') => {
                    self.i += 1;
                    return Ok(String::from_utf8_lossy(&out).into_owned());
                }
                Some(c) => {
                    out.push(c);
                    self.i += 1;
                }
                None => return Err(format!("a text opened at byte {start} is not closed")),
            }
        }
    }
}

const GEOGRAPHIC: [&str; 3] = ["GEOGCS", "GEOGCRS", "GEOGRAPHICCRS"];
const GEODETIC: [&str; 2] = ["GEODCRS", "GEODETICCRS"];
const VERTICAL: [&str; 4] = ["VERT_CS", "VERTCS", "VERTCRS", "VERTICALCRS"];
const UNIT: [&str; 2] = ["UNIT", "LENGTHUNIT"];

/// A bound CRS (WKT 2) stands for its source CRS.
fn unbound(node: &WktNode) -> &WktNode {
    if node.keyword == "BOUNDCRS" {
        if let Some(inner) = node.child(&["SOURCECRS"]).and_then(|s| s.children().next()) {
            return inner;
        }
    }
    node
}

/// A `UNIT`/`LENGTHUNIT` node's name and size in metres.
fn unit_of(node: &WktNode) -> Option<LengthUnit> {
    let metres = node.items.iter().find_map(|i| match i {
        Wkt::Word(w) => w.parse::<f64>().ok(),
        _ => None,
    })?;
    (metres.is_finite() && metres > 0.0).then(|| LengthUnit::new(&node.name(), metres))
}

/// A CRS node's length unit: its own `UNIT` (WKT 1, and WKT 2's short form)
/// or its first axis's (WKT 2). A projection's parameters (WKT 2's
/// `CONVERSION`) carry their own units and are not looked into.
fn crs_length_unit(crs: &WktNode) -> Option<LengthUnit> {
    crs.child(&UNIT)
        .or_else(|| {
            crs.children()
                .filter(|n| n.keyword == "AXIS")
                .find_map(|a| a.child(&UNIT))
        })
        .and_then(unit_of)
}

/// True for a WKT 2 geodetic CRS on an ellipsoidal coordinate system.
fn is_ellipsoidal(crs: &WktNode) -> bool {
    crs.child(&["CS"]).is_some_and(|cs| {
        cs.items
            .iter()
            .any(|i| matches!(i, Wkt::Word(w) if w.eq_ignore_ascii_case("ellipsoidal")))
    })
}

fn wkt_units(root: &WktNode) -> CrsUnits {
    let source = "its WKT record".to_string();
    let root = unbound(root);
    let (horizontal, vertical) = if ["COMPD_CS", "COMPOUNDCRS"].contains(&root.keyword.as_str()) {
        let parts: Vec<&WktNode> = root.children().map(unbound).collect();
        (
            parts.iter().copied().find(|n| {
                !VERTICAL.contains(&n.keyword.as_str())
                    && n.keyword != "AUTHORITY"
                    && n.keyword != "ID"
            }),
            parts
                .iter()
                .copied()
                .find(|n| VERTICAL.contains(&n.keyword.as_str())),
        )
    } else if VERTICAL.contains(&root.keyword.as_str()) {
        (None, Some(root))
    } else {
        (Some(root), None)
    };
    let horizontal_unit = match horizontal {
        Some(h)
            if GEOGRAPHIC.contains(&h.keyword.as_str())
                || (GEODETIC.contains(&h.keyword.as_str()) && is_ellipsoidal(h)) =>
        {
            return CrsUnits::Geographic {
                name: h.name(),
                source,
            }
        }
        Some(h) => crs_length_unit(h),
        None => None,
    };
    linear(horizontal_unit, vertical.and_then(crs_length_unit), source)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gt(keys: &[GeoKey]) -> Result<CrsUnits, String> {
        geotiff_units(keys, Path::new("test.las"))
    }

    fn units(wkt: &str) -> CrsUnits {
        wkt_units(&parse_wkt(wkt).unwrap())
    }

    fn sizes(u: &CrsUnits) -> (f64, f64) {
        match u {
            CrsUnits::Linear {
                horizontal,
                vertical,
                ..
            } => (horizontal.metres, vertical.metres),
            other => panic!("not linear: {other:?}"),
        }
    }

    const GEOGCS_NAD83: &str = r#"GEOGCS["NAD83",DATUM["North_American_Datum_1983",SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]]]"#;

    #[test]
    fn wkt1_projected_in_us_survey_feet_with_a_vertical_crs_in_metres() {
        let projcs = format!(
            r#"PROJCS["NAD83 / New York Long Island (ftUS)",{GEOGCS_NAD83},PROJECTION["Lambert_Conformal_Conic_2SP"],PARAMETER["false_easting",984250],UNIT["US survey foot",0.3048006096012192,AUTHORITY["EPSG","9003"]],AXIS["X",EAST],AUTHORITY["EPSG","2263"]]"#
        );
        let u = units(&projcs);
        assert_eq!(sizes(&u), (0.3048006096012192, 0.3048006096012192));
        // The vertical part of a compound CRS has its own unit.
        let compound = format!(
            r#"COMPD_CS["NY + NAVD88",{projcs},VERT_CS["NAVD88 height",VERT_DATUM["North American Vertical Datum 1988",2005],UNIT["metre",1],AXIS["Up",UP]]]"#
        );
        assert_eq!(sizes(&units(&compound)), (0.3048006096012192, 1.0));
        // Parentheses, lower case, spaces, a text with a quote in it.
        let loose =
            r#" projcs ( "a ""quoted"" name" , unit ( "Foot_US" , 0.30480060960121924 ) ) "#;
        assert_eq!(sizes(&units(loose)).0, 0.30480060960121924);
    }

    #[test]
    fn wkt2_units_come_from_the_axes_not_the_projection_parameters() {
        let wkt = r#"PROJCRS["NAD83(2011) / California zone 3 (ftUS)",BASEGEOGCRS["NAD83(2011)",DATUM["NAD83 (National Spatial Reference System 2011)",ELLIPSOID["GRS 1980",6378137,298.257222101,LENGTHUNIT["metre",1]]],ANGLEUNIT["degree",0.0174532925199433]],CONVERSION["SPCS83 California zone 3 (US survey foot)",METHOD["Lambert Conic Conformal (2SP)"],PARAMETER["False easting",2000000,LENGTHUNIT["metre",1]]],CS[Cartesian,2],AXIS["easting (X)",east,ORDER[1],LENGTHUNIT["US survey foot",0.304800609601219]],AXIS["northing (Y)",north,ORDER[2],LENGTHUNIT["US survey foot",0.304800609601219]],ID["EPSG",6420]]"#;
        assert_eq!(sizes(&units(wkt)), (0.304800609601219, 0.304800609601219));
        let utm = r#"PROJCRS["WGS 84 / UTM zone 33N",BASEGEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563]]],CONVERSION["UTM zone 33N",METHOD["Transverse Mercator"]],CS[Cartesian,2],AXIS["(E)",east],AXIS["(N)",north],LENGTHUNIT["metre",1]]"#;
        assert_eq!(sizes(&units(utm)), (1.0, 1.0));
        let bound = format!(
            r#"BOUNDCRS[SOURCECRS[{wkt}],TARGETCRS[{utm}],ABRIDGEDTRANSFORMATION["x",METHOD["y"]]]"#
        );
        assert_eq!(sizes(&units(&bound)).0, 0.304800609601219);
    }

    #[test]
    fn geographic_crs_are_told_apart_from_geocentric_ones() {
        assert!(
            matches!(units(GEOGCS_NAD83), CrsUnits::Geographic { name, .. } if name == "NAD83")
        );
        let geog2 = r#"GEOGCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563]],CS[ellipsoidal,2],AXIS["latitude",north],AXIS["longitude",east],ANGLEUNIT["degree",0.0174532925199433]]"#;
        assert!(matches!(units(geog2), CrsUnits::Geographic { .. }));
        let geocentric = r#"GEODCRS["WGS 84",DATUM["World Geodetic System 1984",ELLIPSOID["WGS 84",6378137,298.257223563]],CS[Cartesian,3],AXIS["(X)",geocentricX],LENGTHUNIT["metre",1]]"#;
        assert_eq!(sizes(&units(geocentric)), (1.0, 1.0));
        // A compound CRS on a geographic base.
        let compound = format!(r#"COMPD_CS["x",{GEOGCS_NAD83},VERT_CS["h",UNIT["metre",1]]]"#);
        assert!(matches!(units(&compound), CrsUnits::Geographic { .. }));
        // A CRS without a length unit says nothing.
        assert_eq!(units(r#"LOCAL_CS["site"]"#), CrsUnits::Unstated);
    }

    #[test]
    fn malformed_wkt_is_an_error_not_a_panic() {
        for bad in [
            "",
            "PROJCS",
            r#"PROJCS["a""#,
            r#"PROJCS["a",UNIT["ft",0.3]"#,
            r#"PROJCS["a"] trailing"#,
            r#"PROJCS["a",,]"#,
        ] {
            assert!(parse_wkt(bad).is_err(), "{bad:?}");
        }
        let deep = format!("{}{}", "A[".repeat(200), "]".repeat(200));
        assert!(parse_wkt(&deep).is_err());
    }

    #[test]
    fn geotiff_keys_give_units_by_code_or_by_the_crs_code() {
        let keys = |pairs: &[(u16, u16)]| -> Vec<GeoKey> {
            pairs
                .iter()
                .map(|&(id, v)| GeoKey {
                    id,
                    value: GeoValue::Short(v),
                })
                .collect()
        };
        // Units stated by key.
        let u = gt(&keys(&[
            (1024, 1),
            (3072, 32767),
            (3076, 9002),
            (4099, 9001),
        ]))
        .unwrap();
        assert_eq!(sizes(&u), (FOOT_M, 1.0));
        // Only the projected CRS's EPSG code: NY Long Island in US survey
        // feet, UTM 33N in metres, and 4326, geographic.
        let u = gt(&keys(&[(1024, 1), (3072, 2263)])).unwrap();
        assert_eq!(sizes(&u), (US_SURVEY_FOOT_M, US_SURVEY_FOOT_M));
        assert_eq!(sizes(&gt(&keys(&[(3072, 32633)])).unwrap()), (1.0, 1.0));
        assert!(matches!(
            gt(&keys(&[(3072, 4326)])).unwrap(),
            CrsUnits::Geographic { name, .. } if name == "EPSG:4326"
        ));
        assert!(matches!(
            gt(&keys(&[(1024, 2), (2048, 4269)])).unwrap(),
            CrsUnits::Geographic { .. }
        ));
        // A unit code not known is an error that names it; no keys, unstated.
        let err = gt(&keys(&[(3076, 9014)])).unwrap_err();
        assert!(err.contains("EPSG:9014"), "{err}");
        assert_eq!(gt(&[]).unwrap(), CrsUnits::Unstated);
        // A user-defined unit with its size.
        let mut user = keys(&[(3076, 32767)]);
        user.push(GeoKey {
            id: 3077,
            value: GeoValue::Double(0.5),
        });
        assert_eq!(sizes(&gt(&user).unwrap()), (0.5, 0.5));
        // A vertical CRS without a vertical unit key: its unit from the
        // table (NAVD88 in metres under US-feet coordinates), else the
        // horizontal unit; a user-defined vertical unit has no size key.
        let u = gt(&keys(&[(1024, 1), (3072, 2263), (4096, 5703)])).unwrap();
        assert_eq!(sizes(&u), (US_SURVEY_FOOT_M, 1.0));
        let u = gt(&keys(&[(1024, 1), (3076, 9001), (4096, 6360)])).unwrap();
        assert_eq!(sizes(&u), (1.0, US_SURVEY_FOOT_M));
        let u = gt(&keys(&[(1024, 1), (3076, 9002), (4096, 9999)])).unwrap();
        assert_eq!(sizes(&u), (FOOT_M, FOOT_M));
        let err = gt(&keys(&[(3076, 9001), (4099, 32767)])).unwrap_err();
        assert!(err.contains("key 4099") && err.contains("size"), "{err}");
    }

    #[test]
    fn esri_wkt_with_a_vertical_crs_beside_the_projected_one() {
        // ArcGIS writes the two CRSs side by side, not in a COMPD_CS.
        let esri = r#"PROJCS["NAD_1983_StatePlane_New_York_Long_Island_FIPS_3104_Feet",GEOGCS["GCS_North_American_1983",DATUM["D_North_American_1983",SPHEROID["GRS_1980",6378137.0,298.257222101]],PRIMEM["Greenwich",0.0],UNIT["Degree",0.0174532925199433]],PROJECTION["Lambert_Conformal_Conic"],PARAMETER["False_Easting",984250.0],UNIT["Foot_US",0.3048006096012192]],VERTCS["NAVD_1988",VDATUM["North_American_Vertical_Datum_1988"],PARAMETER["Vertical_Shift",0.0],PARAMETER["Direction",1.0],UNIT["Meter",1.0]]"#;
        assert_eq!(sizes(&units(esri)), (0.3048006096012192, 1.0));
        // A VERTCS alone sets z only.
        let vertcs = r#"VERTCS["NAVD_1988",VDATUM["x"],UNIT["Foot_US",0.3048006096012192]]"#;
        assert_eq!(sizes(&units(vertcs)), (1.0, 0.3048006096012192));
    }

    #[test]
    fn input_units_parse() {
        assert_eq!(
            InputUnits::parse("us-ft").unwrap(),
            InputUnits::UsSurveyFoot
        );
        assert_eq!(InputUnits::parse(" FT ").unwrap(), InputUnits::Foot);
        assert_eq!(InputUnits::parse("meters").unwrap(), InputUnits::Metre);
        assert_eq!(InputUnits::parse("auto").unwrap(), InputUnits::Auto);
        assert!(InputUnits::parse("yards").unwrap_err().contains("`yards`"));
        assert_eq!(
            InputUnits::UsSurveyFoot.unit().unwrap().metres,
            1200.0 / 3937.0
        );
    }
}
