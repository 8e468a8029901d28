// Decodes a KHR_draco_mesh_compression GLB with Google's Draco decoder (draco3dgltf, through
// gltf-transform) and writes it without the extension: the reference twin the Rust tests
// compare willow's own Draco decoding with. Usage: node draco_to_plain.mjs IN.glb OUT.glb
import { NodeIO } from '@gltf-transform/core';
import { ALL_EXTENSIONS } from '@gltf-transform/extensions';
import draco3d from 'draco3dgltf';

const [input, output] = process.argv.slice(2);
const io = new NodeIO()
    .registerExtensions(ALL_EXTENSIONS)
    .registerDependencies({ 'draco3d.decoder': await draco3d.createDecoderModule() });
const doc = await io.read(input);
for (const ext of doc.getRoot().listExtensionsUsed()) {
    if (ext.extensionName === 'KHR_draco_mesh_compression') ext.dispose();
}
await io.write(output, doc);
