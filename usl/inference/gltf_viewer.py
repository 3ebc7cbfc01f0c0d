"""A self-contained HTML page that shows a prediction GLB as the input camera saw it.

The page needs no network: three.js, its GLTFLoader and TrackballControls come from the copy
trimesh ships (``trimesh/resources/templates/viewer.zip``), and the GLB is inlined as base64.
trimesh's own page lights the scene from the camera's position with a directional light aimed
at the camera itself (so nothing is lit when the camera sits at the origin) and shows the scene
from a corner; this page instead

* opens at the input camera's viewpoint, with the full K of the camera's ``extras``
  (``usl.inference.gltf_scene.camera_extras``; an off-centre principal point becomes a view offset)
  and the canvas at the image's aspect ratio, so the objects overlay the image as in the input;
* lights the objects with an ambient light and a head light that moves with the camera (the
  image plane's material is unlit in the GLB: it shows the image's own colours), and
* orbits (drag), zooms (wheel) and pans (right drag) about the objects' centre.
"""

from __future__ import annotations

import base64
from functools import lru_cache

from usl.inference.gltf_scene import IMAGE_NODE

_LIBRARY_END = "var camera,controls,scene,renderer,tracklight;"  # trimesh's page code starts here

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
html, body {{ margin: 0; height: 100%; background: #202020; overflow: hidden; }}
canvas {{ position: absolute; display: block; }}
#help {{ position: absolute; right: 8px; bottom: 6px; color: #aaa; font: 12px sans-serif; }}
</style>
</head>
<body>
<div id="help">drag: orbit, wheel: zoom, right drag: pan</div>
<script>{library}</script>
<script>
const IMAGE_NODE = "{image_node}";
const GLB = "{glb}";
let camera, controls, renderer, scene, imageAspect = 1;

function fitCanvas() {{
  // the largest rectangle of the image's aspect ratio inside the window, centred
  let w = window.innerWidth, h = window.innerHeight;
  if (w / h > imageAspect) w = h * imageAspect; else h = w / imageAspect;
  renderer.setSize(Math.round(w), Math.round(h));
  renderer.domElement.style.left = Math.round((window.innerWidth - w) / 2) + "px";
  renderer.domElement.style.top = Math.round((window.innerHeight - h) / 2) + "px";
  if (controls) controls.handleResize();
  render();
}}

function useIntrinsics(cam, extras) {{
  // K with pixel centres at +0.5: a symmetric frustum around the principal point, cropped to the image
  const K = extras.K, W = extras.image_size[0], H = extras.image_size[1];
  const fx = K[0][0], fy = K[1][1], cx = K[0][2], cy = K[1][2];
  const fullW = 2 * Math.max(cx, W - cx), fullH = 2 * Math.max(cy, H - cy);
  cam.fov = 2 * Math.atan(0.5 * fullH / fy) * 180 / Math.PI;
  cam.aspect = (fullW / fx) / (fullH / fy);
  cam.setViewOffset(fullW, fullH, 0.5 * fullW - cx, 0.5 * fullH - cy, W, H);
  return W / H;  // the canvas shows the image's pixels
}}

function render() {{ if (camera) renderer.render(scene, camera); }}

function animate() {{ requestAnimationFrame(animate); controls.update(); }}

function init() {{
  scene = new THREE.Scene();
  scene.background = new THREE.Color(0x202020);
  renderer = new THREE.WebGLRenderer({{antialias: true, preserveDrawingBuffer: true}});
  renderer.outputEncoding = THREE.sRGBEncoding;
  document.body.appendChild(renderer.domElement);
  new THREE.GLTFLoader().load("data:application/octet-stream;base64," + GLB, function (gltf) {{
    scene.add(gltf.scene);
    scene.updateMatrixWorld(true);
    camera = gltf.cameras[0];
    scene.attach(camera);  // world pose kept; the controls move it in world coordinates
    const extras = camera.userData || {{}};
    imageAspect = extras.K ? useIntrinsics(camera, extras) : camera.aspect;
    camera.near = 0.01; camera.far = 1000; camera.updateProjectionMatrix();
    camera.up.set(0, 1, 0).applyQuaternion(camera.quaternion);
    const objects = new THREE.Box3();
    gltf.scene.traverse(function (node) {{
      let isImage = node.name === IMAGE_NODE;
      node.traverseAncestors(function (a) {{ if (a.name === IMAGE_NODE) isImage = true; }});
      if (node.isMesh && !isImage) objects.expandByObject(node);
    }});
    scene.add(new THREE.AmbientLight(0xffffff, 0.45));
    const headlight = new THREE.DirectionalLight(0xffffff, 0.9);
    headlight.position.set(0.3, 0.5, 0);  // a little above and right of the eye, for shading
    headlight.target.position.set(0, 0, -1);
    camera.add(headlight, headlight.target);
    const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(camera.quaternion);
    let distance = 2;
    if (!objects.isEmpty()) {{
      const centre = objects.getCenter(new THREE.Vector3());
      distance = Math.max(centre.sub(camera.position).dot(forward), 0.1);
    }}
    controls = new THREE.TrackballControls(camera, renderer.domElement);
    controls.rotateSpeed = 2.0; controls.staticMoving = true;
    controls.target.copy(camera.position).addScaledVector(forward, distance);  // on the optical axis
    controls.addEventListener("change", render);
    window.addEventListener("resize", fitCanvas);
    fitCanvas();
    animate();
  }}, undefined, function (error) {{
    document.body.insertAdjacentHTML("beforeend", "<pre style='color:#f66'>" + error + "</pre>");
  }});
}}
init();
</script>
</body>
</html>
"""


@lru_cache(maxsize=1)
def three_js_library() -> str:
    """three.js with GLTFLoader and TrackballControls, as trimesh bundles them (minified, MIT)."""
    from trimesh import resources, util

    archive = util.decompress(resources.get_bytes("templates/viewer.zip"), file_type="zip")
    page = archive["viewer.html.template"].read().decode("utf-8")
    start, end = page.find("<script>"), page.find(_LIBRARY_END)
    if start < 0 or end < 0:
        raise RuntimeError("this trimesh's viewer template has an unexpected layout: cannot take three.js from it")
    return page[start + len("<script>") : end]


def viewer_html(glb: bytes, title: str = "usl prediction") -> str:
    """The page showing ``glb`` (a ``usl.inference.gltf_scene.scene_glb`` file); works from ``file://``, offline."""
    return _PAGE.format(
        title=title.replace("<", "&lt;"),
        library=three_js_library(),
        image_node=IMAGE_NODE,
        glb=base64.b64encode(glb).decode("ascii"),
    )
