#version 450
// One-pass forward shader for small CPU-rendered (lavapipe) RGB-D sensors. Derived from SAPIEN's
// "minimal" shader pack (Apache-2.0, Copyright 2020-2024 UCSD SU Lab, 2025 Hillbot Inc.).

layout(set = 0, binding = 0) uniform CameraBuffer {
  mat4 viewMatrix;
  mat4 projectionMatrix;
  mat4 viewMatrixInverse;
  mat4 projectionMatrixInverse;
  float width;
  float height;
} cameraBuffer;

layout(set = 1, binding = 0) uniform ObjectTransformBuffer {
  mat4 modelMatrix;
} objectTransformBuffer;

layout(set = 1, binding = 1) uniform ObjectDataBuffer {
  uvec4 segmentation;
  float transparency;
  int shadeFlat;
} objectDataBuffer;

layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in vec2 uv;
layout(location = 3) in vec3 tangent;
layout(location = 4) in vec3 bitangent;

layout(location = 0) out vec4 outPosition;
layout(location = 1) out vec2 outUV;
layout(location = 2) out flat uvec4 outSegmentation;
layout(location = 3) out vec3 outNormal;

void main() {
  outSegmentation = objectDataBuffer.segmentation;
  mat4 modelView = cameraBuffer.viewMatrix * objectTransformBuffer.modelMatrix;
  outPosition = modelView * vec4(position, 1);
  outUV = uv;
  outNormal = normalize(transpose(inverse(mat3(modelView))) * normal);
  gl_Position = cameraBuffer.projectionMatrix * outPosition;
}
