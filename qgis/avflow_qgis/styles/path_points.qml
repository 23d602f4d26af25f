<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="Symbology|Labeling">
  <renderer-v2 type="singleSymbol" symbollevels="0" enableorderby="0" forceraster="0">
    <symbols>
      <symbol name="0" type="marker" alpha="1" clip_to_extent="1" force_rhr="0">
        <layer class="SimpleMarker" enabled="1" locked="0" pass="0"><Option type="Map">
          <Option name="name" value="diamond" type="QString"/><Option name="color" value="255,255,255,255" type="QString"/>
          <Option name="outline_color" value="30,30,30,255" type="QString"/><Option name="outline_width" value="0.4" type="QString"/>
          <Option name="size" value="3" type="QString"/><Option name="size_unit" value="MM" type="QString"/></Option></layer>
      </symbol>
    </symbols>
  </renderer-v2>
  <labeling type="simple">
    <settings calloutType="simple">
      <text-style fieldName="point" fontSize="8" fontFamily="DejaVu Sans" textColor="30,30,30,255" isExpression="0">
        <text-buffer bufferDraw="1" bufferSize="0.8" bufferColor="255,255,255,255"/>
      </text-style>
      <placement placement="1" dist="1.5" quadOffset="5"/>
    </settings>
  </labeling>
</qgis>
