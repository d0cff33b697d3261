//! Pinhole cameras, as glTF defines them: the camera looks down its node's local −Z with +Y up;
//! `yfov` is the vertical field of view. The aspect ratio is the image's (width / height), so a
//! sidecar's image size wins over a glTF `aspectRatio`.

use glam::{Mat3, Mat4, Vec3};

/// A perspective camera placed in the world.
#[derive(Debug, Clone)]
pub struct Camera {
    /// The glTF camera node's name (or the camera's, if the node has none).
    pub name: String,
    /// Camera position, world space (metres).
    pub origin_world: Vec3,
    /// Rotation camera → world (columns: camera +X right, +Y up, +Z back), orthonormal.
    pub world_from_camera: Mat3,
    /// Vertical field of view in radians, in (0, π).
    pub yfov: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// The glTF camera's `aspectRatio` (width / height), if it states one. The image size
    /// decides the rendered aspect; this checks that images given for the view fit it.
    pub aspect_ratio: Option<f32>,
}

impl Camera {
    /// A camera from a node's world transform; scale and shear are removed (a camera is rigid).
    pub fn from_node(
        name: String,
        world_from_node: Mat4,
        yfov: f32,
        width: u32,
        height: u32,
    ) -> Self {
        let (_, rotation, translation) = world_from_node.to_scale_rotation_translation();
        Camera {
            name,
            origin_world: translation,
            world_from_camera: Mat3::from_quat(rotation.normalize()),
            yfov,
            width,
            height,
            aspect_ratio: None,
        }
    }

    /// A camera at `eye` looking at `target` with `up` upward in its image; None when the
    /// eye is the target or `up` is along the line of sight (no direction or no up).
    pub fn looking_at(
        name: &str,
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        yfov: f32,
        width: u32,
        height: u32,
    ) -> Option<Self> {
        let back = (eye - target).try_normalize()?;
        let right = up.cross(back).try_normalize()?;
        Some(Camera {
            name: name.to_string(),
            origin_world: eye,
            world_from_camera: Mat3::from_cols(right, back.cross(right), back),
            yfov,
            width,
            height,
            aspect_ratio: None,
        })
    }

    /// A camera at `eye` looking at `target`, world +Y up (for tests and tools).
    pub fn look_at(
        name: &str,
        eye: Vec3,
        target: Vec3,
        yfov: f32,
        width: u32,
        height: u32,
    ) -> Self {
        let back = (eye - target).normalize();
        let right = Vec3::Y.cross(back).normalize();
        let up = back.cross(right);
        Camera {
            name: name.to_string(),
            origin_world: eye,
            world_from_camera: Mat3::from_cols(right, up, back),
            yfov,
            width,
            height,
            aspect_ratio: None,
        }
    }

    /// The unit direction (world space) through a continuous image position: `x` grows right
    /// and `y` grows down, pixel (i, j) covers [i, i+1) × [j, j+1), row 0 is the top.
    #[inline]
    pub fn ray_dir_world(&self, x: f32, y: f32) -> Vec3 {
        self.ray_dirs()(x, y)
    }

    /// [`Camera::ray_dir_world`] with the per-camera constants computed once (the render
    /// loop calls it for every sample).
    #[inline]
    pub fn ray_dirs(&self) -> impl Fn(f32, f32) -> Vec3 + Sync + '_ {
        let tan_half = (0.5 * self.yfov).tan();
        let aspect = self.width as f32 / self.height as f32;
        let (w, h) = (self.width as f32, self.height as f32);
        move |x, y| {
            let cx = (2.0 * x / w - 1.0) * tan_half * aspect;
            let cy = (1.0 - 2.0 * y / h) * tan_half;
            (self.world_from_camera * Vec3::new(cx, cy, -1.0)).normalize()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_ray_looks_at_target_and_rows_go_down() {
        let cam = Camera::look_at("c", Vec3::new(0.0, 1.0, 3.0), Vec3::ZERO, 0.8, 128, 96);
        let d = cam.ray_dir_world(64.0, 48.0);
        assert!((d - (-cam.origin_world).normalize()).length() < 1e-5);
        // Row 0 is the top: its rays point higher than the bottom row's.
        assert!(cam.ray_dir_world(64.0, 0.0).y > cam.ray_dir_world(64.0, 96.0).y);
        // Column 0 is the left (−X when looking down −Z from +Z).
        assert!(cam.ray_dir_world(0.0, 48.0).x < 0.0);
        // The vertical extent spans exactly yfov.
        let top = cam.ray_dir_world(64.0, 0.0);
        let bottom = cam.ray_dir_world(64.0, 96.0);
        assert!((top.angle_between(bottom) - 0.8).abs() < 1e-5);
    }

    #[test]
    fn from_node_matches_look_at() {
        let a = Camera::look_at(
            "c",
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(0.0, 0.5, 0.0),
            0.7,
            64,
            48,
        );
        let m = Mat4::from_mat3(a.world_from_camera * 2.0).mul_mat4(&Mat4::IDENTITY);
        let m = Mat4::from_translation(a.origin_world) * m;
        let b = Camera::from_node("c".into(), m, 0.7, 64, 48);
        for (x, y) in [(0.0, 0.0), (10.5, 20.25), (64.0, 48.0)] {
            assert!((a.ray_dir_world(x, y) - b.ray_dir_world(x, y)).length() < 1e-5);
        }
    }
}
