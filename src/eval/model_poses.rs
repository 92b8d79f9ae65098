//! Reads the image poses (name -> `cam_from_world`) of a COLMAP model folder,
//! text (`images.txt`) or binary (`images.bin`).
//!
//! Only what the evaluation needs; this is the single call site to switch to
//! `crate::io::model::read_model` once that reader exists.
use std::collections::BTreeMap;
use std::fs;
use std::path::Path;

use super::EvalError;
use crate::scene::Rigid3;

/// Poses by image name. Prefers `images.bin` when both files exist (as COLMAP does).
pub fn load_poses(dir: &Path) -> Result<BTreeMap<String, Rigid3>, EvalError> {
    let bin = dir.join("images.bin");
    let txt = dir.join("images.txt");
    if bin.is_file() {
        read_images_bin(&bin)
    } else if txt.is_file() {
        read_images_txt(&txt)
    } else {
        Err(EvalError::Model {
            path: dir.to_path_buf(),
            message: "no images.bin or images.txt in this folder".into(),
        })
    }
}

fn bad(path: &Path, message: String) -> EvalError {
    EvalError::Model {
        path: path.to_path_buf(),
        message,
    }
}

fn insert(
    out: &mut BTreeMap<String, Rigid3>,
    path: &Path,
    name: String,
    pose: Rigid3,
) -> Result<(), EvalError> {
    if out.insert(name.clone(), pose).is_some() {
        return Err(bad(path, format!("image name {name:?} appears twice")));
    }
    Ok(())
}

fn read_images_txt(path: &Path) -> Result<BTreeMap<String, Rigid3>, EvalError> {
    let text = fs::read_to_string(path).map_err(|e| bad(path, e.to_string()))?;
    let mut out = BTreeMap::new();
    // Data lines alternate: pose line, then the 2D points line (possibly empty).
    let mut expect_pose = true;
    for (lineno, line) in text.lines().enumerate() {
        if line.starts_with('#') {
            continue;
        }
        if !expect_pose {
            expect_pose = true;
            continue;
        }
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 10 {
            return Err(bad(
                path,
                format!(
                    "line {}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME",
                    lineno + 1
                ),
            ));
        }
        let num = |i: usize| -> Result<f64, EvalError> {
            f[i].parse::<f64>().map_err(|_| {
                bad(
                    path,
                    format!(
                        "line {}: field {} is not a number: {:?}",
                        lineno + 1,
                        i + 1,
                        f[i]
                    ),
                )
            })
        };
        let pose = Rigid3::from_colmap(
            [num(1)?, num(2)?, num(3)?, num(4)?],
            [num(5)?, num(6)?, num(7)?],
        );
        // Names may contain spaces: everything after CAMERA_ID.
        let name = f[9..].join(" ");
        insert(&mut out, path, name, pose)?;
        expect_pose = false;
    }
    Ok(out)
}

struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], EvalError> {
        if self.pos + n > self.data.len() {
            return Err(bad(self.path, format!("truncated at byte {}", self.pos)));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, EvalError> {
        // `take` returned exactly 4 bytes.
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn u64(&mut self) -> Result<u64, EvalError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    fn f64(&mut self) -> Result<f64, EvalError> {
        Ok(f64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
}

fn read_images_bin(path: &Path) -> Result<BTreeMap<String, Rigid3>, EvalError> {
    let data = fs::read(path).map_err(|e| bad(path, e.to_string()))?;
    let mut r = Reader {
        data: &data,
        pos: 0,
        path,
    };
    let n = r.u64()?;
    let mut out = BTreeMap::new();
    for _ in 0..n {
        let _image_id = r.u32()?;
        let q = [r.f64()?, r.f64()?, r.f64()?, r.f64()?];
        let t = [r.f64()?, r.f64()?, r.f64()?];
        let _camera_id = r.u32()?;
        let start = r.pos;
        let end = data[start..]
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| bad(path, "unterminated image name".into()))?;
        let name = String::from_utf8_lossy(&data[start..start + end]).into_owned();
        r.pos = start + end + 1;
        let num_points = r.u64()?;
        let skip = usize::try_from(num_points)
            .ok()
            .and_then(|k| k.checked_mul(24))
            .ok_or_else(|| bad(path, "bad point count".into()))?;
        r.take(skip)?;
        insert(&mut out, path, name, Rigid3::from_colmap(q, t))?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_and_binary_agree() {
        let dir = tempfile::tempdir().unwrap();
        let poses = [
            (
                "a b.jpg",
                Rigid3::from_colmap([0.9, 0.1, -0.2, 0.3], [1.0, 2.0, 3.0]),
            ),
            (
                "c.jpg",
                Rigid3::from_colmap([1.0, 0.0, 0.0, 0.0], [-4.0, 5.5, 4.4e6]),
            ),
        ];
        let mut txt = String::from("# header\n");
        let mut bin: Vec<u8> = (poses.len() as u64).to_le_bytes().to_vec();
        for (i, (name, p)) in poses.iter().enumerate() {
            let q = p.quaternion_wxyz();
            let t = p.translation;
            txt += &format!(
                "{} {} {} {} {} {} {} {} 1 {}\n",
                i + 1,
                q[0],
                q[1],
                q[2],
                q[3],
                t.x,
                t.y,
                t.z,
                name
            );
            txt += if i == 0 {
                "10.5 20.5 -1 11 12 3\n"
            } else {
                "\n"
            };
            bin.extend((i as u32 + 1).to_le_bytes());
            for v in q.iter().chain(t.as_slice()) {
                bin.extend(v.to_le_bytes());
            }
            bin.extend(1u32.to_le_bytes());
            bin.extend(name.as_bytes());
            bin.push(0);
            let k: u64 = if i == 0 { 2 } else { 0 };
            bin.extend(k.to_le_bytes());
            bin.extend(vec![0u8; 24 * k as usize]);
        }
        std::fs::write(dir.path().join("images.txt"), txt).unwrap();
        let from_txt = load_poses(dir.path()).unwrap();
        std::fs::write(dir.path().join("images.bin"), &bin).unwrap();
        let from_bin = load_poses(dir.path()).unwrap();
        assert_eq!(from_txt.len(), 2);
        for (name, p) in poses {
            for m in [&from_txt, &from_bin] {
                let got = m[name];
                assert!((got.translation - p.translation).norm() < 1e-9);
                assert!(got.rotation.angle_to(&p.rotation) < 1e-12);
            }
        }
        // Truncated binary: a clear error, no panic.
        std::fs::write(dir.path().join("images.bin"), &bin[..bin.len() - 30]).unwrap();
        assert!(load_poses(dir.path()).is_err());
    }
}
