#version 450
// One-pass forward shader for small CPU-rendered (lavapipe) RGB-D sensors. Derived from SAPIEN's
// "minimal" shader pack (Apache-2.0, Copyright 2020-2024 UCSD SU Lab, 2025 Hillbot Inc.): the same
// GGX + Lambert directional and ambient lighting, written straight to the Color target, so the
// frame needs no second (composite) pass; no shadows, no image-based lighting.

layout (constant_id = 0) const int NUM_DIRECTIONAL_LIGHTS = 0;

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

layout(set = 2, binding = 0) uniform MaterialBuffer {
  vec4 emission;
  vec4 baseColor;
  float fresnel;
  float roughness;
  float metallic;
  float transmission;
  float ior;
  float transmissionRoughness;
  int textureMask;
  int padding1;
  vec4 textureTransforms[6];
} materialBuffer;

layout(set = 2, binding = 1) uniform sampler2D colorTexture;
layout(set = 2, binding = 2) uniform sampler2D roughnessTexture;
layout(set = 2, binding = 3) uniform sampler2D normalTexture;
layout(set = 2, binding = 4) uniform sampler2D metallicTexture;
layout(set = 2, binding = 5) uniform sampler2D emissionTexture;

struct PointLight {
  vec4 position;
  vec4 emission;
};
struct DirectionalLight {
  vec4 direction;
  vec4 emission;
};
struct SpotLight {
  vec4 position;
  vec4 direction;
  vec4 emission;
};

layout(set = 3, binding = 0) uniform SceneBuffer {
  vec4 ambientLight;
  PointLight pointLights[10];
  DirectionalLight directionalLights[3];
  SpotLight spotLights[10];
  SpotLight texturedLights[1];
} sceneBuffer;

layout(location = 0) in vec4 inPosition;
layout(location = 1) in vec2 inUV;
layout(location = 2) in flat uvec4 inSegmentation;
layout(location = 3) in vec3 inNormal;

layout(location = 0) out vec4 outColor;
layout(location = 1) out ivec4 outPositionSegmentation;

const float PI = 3.141592653589793f;

vec3 ggx(float NoL, float NoV, float NoH, float VoH, float roughness, vec3 fresnel) {
  float alpha = roughness * roughness;
  float alpha2 = alpha * alpha;
  float k = (alpha + 2 * roughness + 1.0) / 8.0;
  float FMi = ((-5.55473) * VoH - 6.98316) * VoH;
  vec3 frac = (fresnel + (1 - fresnel) * pow(2.0, FMi)) * alpha2;
  float nom0 = NoH * NoH * (alpha2 - 1) + 1;
  float nom1 = NoV * (1 - k) + k;
  float nom2 = NoL * (1 - k) + k;
  float nom = clamp((4 * PI * nom0 * nom0 * nom1 * nom2), 1e-6, 4 * PI);
  return frac / nom * NoL;
}

void main() {
  vec4 albedo = materialBuffer.baseColor;
  if ((materialBuffer.textureMask & 1) != 0) {
    albedo = texture(colorTexture, inUV * materialBuffer.textureTransforms[0].zw + materialBuffer.textureTransforms[0].xy);
  }
  albedo.a *= (1.f - objectDataBuffer.transparency);
  if (albedo.a == 0) {
    discard;
  }
  float specular = materialBuffer.fresnel * 0.08;
  float roughness = materialBuffer.roughness;
  float metallic = materialBuffer.metallic;

  vec3 normal = normalize(inNormal);
  if (objectDataBuffer.shadeFlat != 0) {
    normal = -normalize(cross(dFdx(inPosition.xyz), dFdy(inPosition.xyz)));
  }
  vec3 camDir = -normalize(inPosition.xyz / inPosition.w);
  vec3 diffuseAlbedo = albedo.rgb * (1 - metallic);
  vec3 fresnel = specular * (1 - metallic) + albedo.rgb * metallic;

  vec3 color = materialBuffer.emission.rgb;
  for (int i = 0; i < NUM_DIRECTIONAL_LIGHTS; ++i) {
    vec3 lightDir = -(mat3(cameraBuffer.viewMatrix) * sceneBuffer.directionalLights[i].direction.xyz);
    vec3 emission = sceneBuffer.directionalLights[i].emission.rgb;
    vec3 H = lightDir + camDir;
    H = dot(H, H) < 1e-6 ? vec3(0) : normalize(H);
    float NoH = clamp(dot(normal, H), 1e-6, 1);
    float VoH = clamp(dot(camDir, H), 1e-6, 1);
    float NoL = clamp(dot(normal, lightDir), 0, 1);
    float NoV = clamp(dot(normal, camDir), 1e-6, 1);
    color += diffuseAlbedo * emission * NoL / PI + emission * ggx(NoL, NoV, NoH, VoH, roughness, fresnel);
  }
  color += sceneBuffer.ambientLight.rgb * albedo.rgb;

  outColor = vec4(clamp(pow(color, vec3(1 / 2.2)), vec3(0), vec3(1)), albedo.a);
  outPositionSegmentation = ivec4(ivec3(inPosition.xyz / inPosition.w * 1000), inSegmentation[1]);
}
