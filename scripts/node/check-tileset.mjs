// Checks a 3D Tiles tileset with independent readers and prints one JSON report:
//   node check-tileset.mjs TILESET_DIR SCHEMA_DIR
// - tileset.json against the 3D Tiles 1.1 JSON schema (Ajv, draft 2020-12);
// - every tile's glTF content with the Khronos glTF validator;
// - the whole tileset read back by loaders.gl's 3D Tiles loader.
// Exit status 0 when the checks ran (the report says whether they passed), 2 when
// they could not run.
import { readFileSync, readdirSync, statSync } from "node:fs";
import { join, relative, dirname } from "node:path";
import Ajv2020 from "ajv/dist/2020.js";
import validator from "gltf-validator";
import { parse } from "@loaders.gl/core";
import { Tiles3DLoader } from "@loaders.gl/3d-tiles";

const [dir, schemaDir] = process.argv.slice(2);
if (!dir || !schemaDir) {
  console.error("usage: node check-tileset.mjs TILESET_DIR SCHEMA_DIR");
  process.exit(2);
}

function schemaFiles(root) {
  const out = [];
  for (const name of readdirSync(root)) {
    const path = join(root, name);
    if (statSync(path).isDirectory()) out.push(...schemaFiles(path));
    else if (name.endsWith(".schema.json")) out.push(path);
  }
  return out;
}

// 1. The schema: every file under one base, so relative $refs resolve by path.
const base = "https://schemas.texel.invalid/3d-tiles/";
const ajv = new Ajv2020({ strict: false, validateFormats: false, allErrors: true });
for (const path of schemaFiles(schemaDir)) {
  const schema = JSON.parse(readFileSync(path, "utf8"));
  schema.$id = base + relative(schemaDir, path).split("\\").join("/");
  ajv.addSchema(schema);
}
const validateTileset = ajv.getSchema(base + "tileset.schema.json");
const tilesetText = readFileSync(join(dir, "tileset.json"), "utf8");
const tileset = JSON.parse(tilesetText);
const schemaOk = validateTileset(tileset);
const schemaErrors = schemaOk
  ? []
  : validateTileset.errors.map((e) => `${e.instancePath} ${e.message}`);

// 2. Every content with the glTF validator.
const tiles = [];
(function walk(tile) {
  if (tile.content && tile.content.uri) tiles.push(tile);
  for (const child of tile.children || []) walk(child);
})(tileset.root);
const uris = tiles.map((t) => t.content.uri);
let gltfErrors = 0;
let gltfWarnings = 0;
const gltfMessages = [];
for (const uri of uris) {
  const bytes = new Uint8Array(readFileSync(join(dir, uri)));
  const report = await validator.validateBytes(bytes, { uri });
  gltfErrors += report.issues.numErrors;
  gltfWarnings += report.issues.numWarnings;
  for (const m of report.issues.messages) {
    if (m.severity <= 1 && gltfMessages.length < 10) {
      gltfMessages.push(`${uri}: ${m.code} ${m.message} at ${m.pointer}`);
    }
  }
}

// 3. loaders.gl reads the tileset and every tile's content; each content's vertices,
//    placed by their node's translation and turned from +y up to +z up as 3D Tiles
//    does, must lie in their tile's bounding box.
const loaded = await parse(readFileSync(join(dir, "tileset.json")), Tiles3DLoader, {
  "3d-tiles": { isTileset: true },
});
let loaderTiles = 0;
let loaderVertices = 0;
let loaderTriangles = 0;
let outsideBox = 0;
for (const tile of tiles) {
  // Geometry only: decoding a tile's atlas image under Node.js would take loaders.gl's
  // polyfills (the glTF validator above checks the images).
  const content = await parse(readFileSync(join(dir, tile.content.uri)), Tiles3DLoader, {
    "3d-tiles": { isTileset: false, loadGLTF: true },
    gltf: { loadImages: false },
  });
  loaderTiles += 1;
  const gltf = content.gltf;
  const box = tile.boundingVolume.box;
  for (const node of gltf.nodes || []) {
    const mesh = typeof node.mesh === "object" ? node.mesh : gltf.meshes[node.mesh];
    const t = node.translation || [0, 0, 0];
    for (const primitive of mesh.primitives) {
      const positions = primitive.attributes.POSITION.value;
      const count = primitive.attributes.POSITION.count;
      loaderVertices += count;
      loaderTriangles += (primitive.indices ? primitive.indices.count : 0) / 3;
      for (let i = 0; i < count; i++) {
        const world = [
          t[0] + positions[3 * i],
          -(t[2] + positions[3 * i + 2]),
          t[1] + positions[3 * i + 1],
        ];
        // Axis-aligned boxes only: the half axes lie on x, y and z.
        const half = [box[3], box[7], box[11]];
        for (let a = 0; a < 3; a++) {
          if (Math.abs(world[a] - box[a]) > half[a] + 1e-3) {
            outsideBox += 1;
            break;
          }
        }
      }
    }
  }
}

console.log(
  JSON.stringify({
    schemaErrors,
    contents: uris.length,
    gltfErrors,
    gltfWarnings,
    gltfMessages,
    loaderRootError: loaded.root ? loaded.root.geometricError : null,
    loaderRootChildren: loaded.root && loaded.root.children ? loaded.root.children.length : 0,
    loaderTiles,
    loaderVertices,
    loaderTriangles,
    outsideBox,
  }),
);
