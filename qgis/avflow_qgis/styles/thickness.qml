<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="Symbology">
  <pipe>
    <provider><resampling enabled="false" zoomedInResamplingMethod="nearestNeighbour" zoomedOutResamplingMethod="nearestNeighbour" maxOversampling="2"/></provider>
    <rasterrenderer type="singlebandpseudocolor" band="1" opacity="0.85" alphaBand="-1" classificationMin="0" classificationMax="5" nodataColor="">
      <rasterTransparency/>
      <minMaxOrigin><limits>None</limits><extent>WholeRaster</extent><statAccuracy>Estimated</statAccuracy><cumulativeCutLower>0.02</cumulativeCutLower><cumulativeCutUpper>0.98</cumulativeCutUpper><stdDevFactor>2</stdDevFactor></minMaxOrigin>
      <rastershader>
        <colorrampshader colorRampType="DISCRETE" classificationMode="3" clip="0" minimumValue="0" maximumValue="5" labelPrecision="2">
          <item alpha="0" value="0.05" label="&lt; 0.05 m" color="#ffffff"/>
          <item alpha="255" value="0.25" label="0.05–0.25 m" color="#fed976"/>
          <item alpha="255" value="0.5" label="0.25–0.5 m" color="#feb24c"/>
          <item alpha="255" value="1.0" label="0.5–1 m" color="#fd8d3c"/>
          <item alpha="255" value="2.0" label="1–2 m" color="#fc4e2a"/>
          <item alpha="255" value="3.0" label="2–3 m" color="#e31a1c"/>
          <item alpha="255" value="5.0" label="3–5 m" color="#bd0026"/>
          <item alpha="255" value="inf" label="≥ 5 m" color="#800026"/>
        </colorrampshader>
      </rastershader>
    </rasterrenderer>
    <brightnesscontrast brightness="0" contrast="0" gamma="1"/>
    <huesaturation saturation="0" grayscaleMode="0" colorizeOn="0" colorizeRed="255" colorizeGreen="128" colorizeBlue="128" colorizeStrength="100"/>
    <rasterresampler maxOversampling="2"/>
  </pipe>
  <blendMode>0</blendMode>
</qgis>
